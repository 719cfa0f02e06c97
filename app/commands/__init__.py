"""Command groups of ``hrc`` that are registered in :mod:`app.cli`: ``hrc hmp ...`` and ``hrc cell ...``.

They live here, above the packages they drive, so that the pure core (:mod:`app.prediction`) and the cell
(:mod:`app.cell`) import no command line and nothing above themselves.
"""
