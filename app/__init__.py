"""Proactive human-aware motion planning for human-robot cooperation (UR5e).

The package is layered: ``planning`` and ``prediction`` are pure computation over numpy/torch arrays;
``control`` runs the cell (clocks, robot backends, human sources, supervisor); ``study`` keeps records;
``api`` and ``ui`` are the web server and the operator's view.
"""

from __future__ import annotations

__version__ = "0.1.0"
