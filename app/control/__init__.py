"""The runtime: the supervisor (the paper's replan state machine), the task executive, the trial engine,
and the live (threads, wall clock) and headless (simulated clock) runners.

What connects to the physical cell (clocks, robot backends, human sources, frame validation) lives in
:mod:`app.cell`; the ISO/TS 15066 safety function in :mod:`app.safety`.
"""
