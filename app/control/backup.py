"""Plan jobs: the backup plans the supervisor asks for under the deadline D, computed by a
:class:`BackupComputer` inline (:class:`InlinePlanJobs`, headless runs) or on a pool of planner threads
(:class:`PoolPlanJobs`, the live runtime), which let each frame's decision go first
(:class:`ForegroundGate`)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import copy
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np

from app.control.trajectory_views import (
    Goal,
    MakeTrajectory,
    PlannerLike,
    RobotGeometry,
    SpeedProfile,
    TrajectoryLike,
)
from app.prediction.forecast import HumanForecast

if TYPE_CHECKING:
    from app.cell.clock import Clock
    from app.planning.search.config import Blocked

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------------------------
# Plan jobs: backup plans under the deadline
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BackupRequest:
    """A backup plan to compute for frame ``key``.

    Attributes:
        key: Frame sequence number.
        t_request: ``T_i``: when the frame arrived (s).
        t_start: When the plan starts (``T_i + D``, or later when the robot holds until then) (s).
        q_start: (6,) start configuration ``pi_curr(T_i + D)``.
        qd_start: (6,) path velocity of the plan in execution at the branch point (scale 1), so that the
            new trajectory continues it.
        goal: Roadmap goal (station name or node index).
        forecast: The forecast of frame ``key``.
        deadline_s: Compute-time budget of this plan: D, or the start deadline for a robot at rest.
        candidate: The reactive method's forecast of the same frame (the person held still where they are
            now): the plan the reactive method would take from the same state is a candidate too
            (:meth:`BackupComputer.compute_raw`). None, or ``forecast`` itself (the reactive method): no
            candidate.
        sets_off: The plan would set a robot at rest moving (a start or a resume), not branch off a plan
            under way.
    """

    key: int
    t_request: float
    t_start: float
    q_start: np.ndarray
    qd_start: np.ndarray
    goal: Goal
    forecast: HumanForecast
    deadline_s: float | None = None
    candidate: HumanForecast | None = None
    sets_off: bool = False

    @property
    def has_candidate(self) -> bool:
        return self.candidate is not None and self.candidate is not self.forecast


#: Which plan a decision with a candidate took: its own forecast's (``forecast``), the reactive method's
#: that arrives earlier under that forecast (``reactive``), or the reactive method's, clear under that
#: forecast, where the forecast's own search found none (``reactive_only``).
PlanChoice = Literal["forecast", "reactive", "reactive_only"]

OutcomeStatus = Literal["ok", "failed", "deadline_miss", "error", "skipped"]


@dataclass(frozen=True, slots=True)
class PlanOutcome:
    """What became of a plan request.

    Attributes:
        status: ``ok``; ``failed`` (the planner found no plan); ``deadline_miss`` (slower than D);
            ``error`` (the planner raised); ``skipped`` (no worker free, or never requested).
        compute_s: Measured compute time (s) of the planner call and the trajectory building.
        traj: The trajectory (when ``ok``).
        profile: Its speed profile (when ``ok``).
        plan: The planner's plan (when ``ok``).
        reason: The planner's reason or the error message.
        arrival_s: When the planner predicts the robot to arrive (s, runtime clock; with SSM-aware timing,
            under the speed governor), or None for the trajectory's end.
        blocked: Of a ``failed`` plan, where the person as forecast was in the way: ``start`` (the robot
            could not leave where it stood) or ``goal`` (occupied); None where the planner found no plan for
            another reason (:attr:`app.planning.search.PlanResult.blocked`).
        chosen: Of a request with a candidate, which plan this is (:data:`PlanChoice`); None without one.
        gain_s: Of a ``reactive`` choice, how much earlier it arrives than the forecast's plan (s).
    """

    status: OutcomeStatus
    compute_s: float = 0.0
    traj: TrajectoryLike | None = None
    profile: SpeedProfile | None = None
    plan: Any = None
    reason: str = ""
    arrival_s: float | None = None
    blocked: Blocked | None = None
    chosen: PlanChoice | None = None
    gain_s: float = 0.0

    def shifted(self, dt_s: float) -> PlanOutcome | None:
        """The same plan ``dt_s`` seconds later (trajectory, profile, plan and predicted arrival); None where
        it is no plan or its trajectory cannot be shifted."""
        shift = getattr(self.traj, "shifted", None)
        if self.status != "ok" or shift is None or self.profile is None:
            return None
        return dataclasses.replace(
            self,
            traj=shift(dt_s),
            profile=dataclasses.replace(self.profile, tau0=self.profile.tau0 + dt_s),
            plan=self.plan.shifted(dt_s) if hasattr(self.plan, "shifted") else self.plan,
            arrival_s=None if self.arrival_s is None else self.arrival_s + dt_s,
        )


class PlanJobs(Protocol):
    """Runs backup plans. ``submit`` at ``T_i``; ``take`` at or after ``T_i + D`` (never blocks long)."""

    def submit(self, request: BackupRequest) -> None: ...

    def take(self, key: int, request: BackupRequest | None = None) -> PlanOutcome: ...

    def peek(self, key: int) -> PlanOutcome | None:
        """The outcome if it is already known without computing anything, else None."""
        ...

    def ready(self, key: int, request: BackupRequest | None = None) -> PlanOutcome | None:
        """The outcome of a request that sets a robot at rest moving, as soon as it is known (its compute time
        counted from the request), else None: the robot may set off before the start deadline."""
        ...

    def foreground(self) -> AbstractContextManager[None]:
        """While the caller is inside it, its work goes before the jobs' (a frame's decision)."""
        ...

    def close(self) -> None: ...


class BackupComputer:
    """Computes one backup plan: planner call, trajectory, speed profile; times the whole of it."""

    def __init__(
        self,
        planner: PlannerLike,
        make_trajectory: MakeTrajectory,
        geometry: RobotGeometry,
        *,
        deadline_s: float,
        workers: int,
        timer: Callable[[], float] = time.perf_counter,
        profile_window_s: float = 0.6,
        timing: Any = None,
    ) -> None:
        self.planner = planner
        #: The governor's model for SSM-aware timing (:class:`app.safety.governor.GovernorModel`), or None.
        self.timing = timing
        self.make_trajectory = make_trajectory
        self.geometry = geometry
        self.deadline_s = float(deadline_s)
        self.workers = int(workers)
        self.timer = timer
        self.profile_window_s = profile_window_s
        #: Give the planner the deadline (live, measured headless); False when compute times are fixed.
        self.enforce_deadline = True

    def reading_clock(self, timer: Callable[[], float]) -> BackupComputer:
        """This computer with its compute times, and its planner's deadlines, read from ``timer``."""
        other = copy.copy(self)
        other.timer = timer
        other.planner = self.planner.with_timer(timer)
        return other

    def __call__(self, req: BackupRequest) -> PlanOutcome:
        """Plan, build the trajectory and its speed profile; ``ok`` or ``deadline_miss`` by the measured
        compute time (see :meth:`judge`)."""
        return self.judge(self.compute_raw(req), None, deadline_s=req.deadline_s)

    def compute_raw(self, req: BackupRequest) -> PlanOutcome:
        """The plan with its measured compute time, not yet judged against the deadline.

        With a candidate (:attr:`BackupRequest.candidate`, the proactive method's requests) the plan the
        reactive method would take from the same state is planned too, with what is left of the deadline,
        and judged under the request's own forecast at the timing the governor is predicted to give it
        (:meth:`PlannerLike.predicted_check`). It is taken where it passes that check and arrives earlier
        than the forecast's plan (``reactive``; weighed where the plan sets a robot at rest moving, whose
        deadline is the longer start deadline), or where the forecast's search found no plan and it passes
        the check (``reactive_only``: the search is more cautious than the check, with its corridor margins
        and its full-speed timing). A reactive plan that the forecast person would meet is never taken:
        the supervisor would have to stop it for them.
        """
        t0 = self.timer()
        budget = (req.deadline_s or self.deadline_s) if self.enforce_deadline else None
        own = self._plan_one(req, req.forecast, budget, t0)
        if not req.has_candidate or own.status == "error" or (own.status == "ok" and not req.sets_off):
            # (a backup of a plan under way that found a plan keeps it: under the deadline D, a second search
            # would cost its compute time on every frame)
            return own
        # (what is left of the budget, less a tenth of it for judging the candidate)
        left = None if budget is None else 0.9 * budget - (self.timer() - t0)
        if left is not None and left <= 0.0:
            return own
        assert req.candidate is not None
        rival = self._plan_one(req, req.candidate, left, self.timer())
        if rival.status != "ok":
            return _kept(own, self.timer() - t0)
        assert rival.traj is not None
        try:
            t_v, arrival = self.planner.predicted_check(rival.traj, req.forecast, timing=self.timing)
        except Exception:  # a candidate that cannot be judged is not taken
            log.exception("judging the reactive candidate of frame %d raised", req.key)
            return _kept(own, self.timer() - t0)
        dt = self.timer() - t0
        if own.status == "ok":
            mine = own.arrival_s if own.arrival_s is not None else own.traj.t_end  # type: ignore[union-attr]
            if t_v is None and arrival < mine:
                return dataclasses.replace(
                    rival, compute_s=dt, arrival_s=arrival, chosen="reactive", gain_s=float(mine - arrival)
                )
            return _kept(own, dt)
        if t_v is None:
            return dataclasses.replace(rival, compute_s=dt, arrival_s=arrival, chosen="reactive_only")
        return _kept(own, dt)

    def _plan_one(
        self, req: BackupRequest, forecast: HumanForecast, budget: float | None, t0: float
    ) -> PlanOutcome:
        """One planner call for ``req`` against ``forecast`` within ``budget`` (s), its trajectory and
        speed profile; the compute time counted from ``t0``."""
        extra = {} if self.timing is None else {"timing": self.timing}
        try:
            res = self.planner.plan(
                q_start=req.q_start,
                t_start=req.t_start,
                goal=req.goal,
                forecast=forecast,
                workers=self.workers,
                deadline_s=budget,
                qd0=req.qd_start,
                **extra,
            )
            if not res.ok or res.plan is None:
                blocked = getattr(res, "blocked", None)
                dt = self.timer() - t0
                return PlanOutcome("failed", compute_s=dt, reason=str(res.reason), blocked=blocked)
            traj = self.make_trajectory(res.plan, req.qd_start)
            prof = SpeedProfile.of(traj, self.geometry, window_s=self.profile_window_s)
        except Exception as exc:  # a planner fault must take the emergency path, never kill the loop
            log.exception("backup plan for frame %d raised", req.key)
            return PlanOutcome("error", compute_s=self.timer() - t0, reason=f"{type(exc).__name__}: {exc}")
        dt = self.timer() - t0
        arrival = getattr(res, "arrival_s", None)
        return PlanOutcome(
            "ok",
            compute_s=dt,
            traj=traj,
            profile=prof,
            plan=res.plan,
            reason=str(res.reason),
            arrival_s=None if arrival is None else float(arrival),
        )

    def judge(
        self, out: PlanOutcome, compute_s: float | None, *, deadline_s: float | None = None
    ) -> PlanOutcome:
        """Apply the deadline (``deadline_s``, default D): a plan slower than it (by ``compute_s`` when
        given, else its measured time) is a ``deadline_miss``, whatever it found; so is a search the
        planner cut at the deadline."""
        c = out.compute_s if compute_s is None else float(compute_s)
        limit = self.deadline_s if deadline_s is None else float(deadline_s)
        if out.status in ("ok", "failed") and (c > limit or out.reason == "deadline"):
            return PlanOutcome("deadline_miss", compute_s=c, reason=f"{c * 1e3:.1f} ms > D ({out.reason})")
        return dataclasses.replace(out, compute_s=c)


def _kept(own: PlanOutcome, compute_s: float) -> PlanOutcome:
    """The forecast's own outcome after a candidate was weighed against it (both compute times counted)."""
    return dataclasses.replace(own, compute_s=compute_s, chosen="forecast" if own.status == "ok" else None)


class InlinePlanJobs:
    """Headless plan jobs: a backup plan is computed only when its own frame's decision consumes it.

    A backup plan of frame ``i`` is used by nothing but the switch that frame ``i``'s decision schedules
    at ``T_i + D`` (later frames branch from the plan in execution at their own time, and a switch
    invalidates backups that branched from the plan it replaces). Computing it when that switch is due and
    charging its measured compute time as if it had started at ``T_i`` therefore gives the same decisions as
    computing every backup eagerly, at a fraction of the cost: a plan slower than ``D`` is a deadline miss,
    exactly as in live mode.

    Args:
        compute: The backup computer.
        fixed_compute_s: When given, the compute time charged for every plan instead of the measured one
            (makes a headless run fully deterministic; used in tests).
        keep: How many pending requests to keep (older ones are dropped: their switch can no longer occur).
    """

    def __init__(
        self, compute: BackupComputer, *, fixed_compute_s: float | None = None, keep: int = 16
    ) -> None:
        self.compute = compute
        self.fixed_compute_s = fixed_compute_s
        compute.enforce_deadline = fixed_compute_s is None
        self._pending: dict[int, BackupRequest] = {}
        self._keep = keep

    def submit(self, request: BackupRequest) -> None:
        self._pending[request.key] = request
        if len(self._pending) > self._keep:
            for k in sorted(self._pending)[: len(self._pending) - self._keep]:
                del self._pending[k]

    def take(self, key: int, request: BackupRequest | None = None) -> PlanOutcome:
        req = self._pending.pop(key, None) or request
        if req is None:
            return PlanOutcome("skipped", reason=f"no backup request for frame {key}")
        return self.compute.judge(
            self.compute.compute_raw(req), self.fixed_compute_s, deadline_s=req.deadline_s
        )

    def peek(self, key: int) -> PlanOutcome | None:
        return None

    def ready(self, key: int, request: BackupRequest | None = None) -> PlanOutcome | None:
        return self.take(key, request)  # computed now, charged from the request: as at the switch

    def foreground(self) -> AbstractContextManager[None]:
        return contextlib.nullcontext()  # a plan is computed only when a decision takes it

    def close(self) -> None:
        self._pending.clear()


class ForegroundGate:
    """Lets one thread's work at a time go before the plan jobs that share the interpreter with it.

    The live runtime's plan jobs run on threads of the process that also runs the frame thread, and the
    interpreter runs one thread's Python at a time: a job between two of its compiled kernels keeps it until
    it is made to switch (every ``sys.getswitchinterval()``, 5 ms), so a frame that arrived while plans were
    computed waited for them, often more than once. While a thread is inside :meth:`foreground` (the frame
    thread, from reading the source to its decision), a job that reads the clock through :meth:`now` (the
    planner does at every step of its search and at every deadline check; the backup computer between its
    steps) waits there until that work is done, ``max_wait_s`` at most, and then goes on. The wait counts in
    the job's compute time and against its deadline, as any delay does. The thread in the foreground never
    waits for itself.

    Args:
        max_wait_s: The longest a job waits at one reading of the clock (a foreground that does not end does
            not stop the jobs).
        timer: The clock read (s).
    """

    def __init__(self, *, max_wait_s: float = 0.02, timer: Callable[[], float] = time.perf_counter) -> None:
        if not max_wait_s > 0:
            raise ValueError(f"ForegroundGate: max_wait_s must be > 0, got {max_wait_s}")
        self.max_wait_s = float(max_wait_s)
        self._timer = timer
        self._free = threading.Event()
        self._free.set()
        self._owner: int | None = None
        self._lock = threading.Lock()
        #: How long the jobs waited for the foreground in all (s), and how often.
        self.waited_s = 0.0
        self.waits = 0

    @contextlib.contextmanager
    def foreground(self) -> Iterator[None]:
        """The caller's work goes first until the block ends (not reentrant)."""
        self._owner = threading.get_ident()
        self._free.clear()
        try:
            yield
        finally:
            self._free.set()

    def now(self) -> float:
        """The time (s), read after the work in the foreground is done where some is under way and the
        caller is not the thread doing it."""
        if self._free.is_set() or threading.get_ident() == self._owner:
            return self._timer()
        t0 = self._timer()
        self._free.wait(self.max_wait_s)
        t = self._timer()
        with self._lock:
            self.waited_s += t - t0
            self.waits += 1
        return t


# ----------------------------------------------------------------------------------------------------
# The supervisor


class PoolPlanJobs:
    """Live plan jobs: every frame's backup plan runs on a pool of ``ceil(D / F)`` workers (more requests
    in flight are skipped); a result is taken at ``T_i + D`` and counts only if it was ready by then.

    The jobs read their clock through a :class:`ForegroundGate`: a thread inside :meth:`foreground` (the
    frame thread, up to its decision) goes before them.

    Args:
        compute: The backup computer (the planner gets the deadline D).
        max_jobs: Jobs in flight at most.
        clock: For the in-flight bookkeeping.
        gate: The jobs' clock (default: a :class:`ForegroundGate` on the computer's timer).
    """

    def __init__(
        self, compute: BackupComputer, *, max_jobs: int, clock: Clock, gate: ForegroundGate | None = None
    ) -> None:
        self.gate = ForegroundGate(timer=compute.timer) if gate is None else gate
        self.compute = compute.reading_clock(self.gate.now)
        self.max_jobs = int(max_jobs)
        self.clock = clock
        self._pool = cf.ThreadPoolExecutor(max_workers=self.max_jobs, thread_name_prefix="hrc-planner")
        self._jobs: dict[int, tuple[cf.Future[PlanOutcome], float]] = {}
        self._lock = threading.Lock()
        self.skipped = 0

    def _in_flight(self) -> int:
        return sum(1 for f, _ in self._jobs.values() if not f.done())

    def submit(self, request: BackupRequest) -> None:
        with self._lock:
            if self._pool is None:
                return
            if self._in_flight() >= self.max_jobs:
                self.skipped += 1
                return
            fut = self._pool.submit(self.compute, request)
            self._jobs[request.key] = (fut, self.clock.now())
            for k in sorted(self._jobs)[: max(len(self._jobs) - 4 * self.max_jobs, 0)]:
                f, _ = self._jobs.pop(k)
                f.cancel()

    def take(self, key: int, request: BackupRequest | None = None) -> PlanOutcome:
        with self._lock:
            job = self._jobs.pop(key, None)
        if job is None:
            return PlanOutcome("skipped", reason=f"no backup job for frame {key} (no worker was free)")
        fut, t_sub = job
        if not fut.done():
            fut.cancel()
            elapsed = self.clock.now() - t_sub
            return PlanOutcome("deadline_miss", compute_s=elapsed, reason="not ready at T_i + D")
        return fut.result()

    def ready(self, key: int, request: BackupRequest | None = None) -> PlanOutcome | None:
        return self.peek(key)

    def peek(self, key: int) -> PlanOutcome | None:
        with self._lock:
            job = self._jobs.get(key)
        if job is None or not job[0].done():
            return None
        return job[0].result()

    def foreground(self) -> AbstractContextManager[None]:
        return self.gate.foreground()

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
            jobs = list(self._jobs.values())
            self._jobs.clear()
        for f, _ in jobs:
            f.cancel()
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
