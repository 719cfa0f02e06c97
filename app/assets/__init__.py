"""Shipped data: the default work cell and the predictor weights."""
