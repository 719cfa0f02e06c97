"""Property tests of the frame validator and the stream parser over arbitrary input: every input gets an
accepted frame or a rejection with a known reason code, counted once, and never another exception (deep
nesting, big sizes, wrong types, integers too large for a float, non-finite numbers)."""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from app.cell.human import StreamSource
from app.cell.stream_protocol import make_message
from app.cell.validation import REJECT_REASONS, FrameRejected, FrameValidator
from app.config import load_workcell
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

CELL = load_workcell()
EXAMPLES = settings(max_examples=2000, deadline=None, suppress_health_check=list(HealthCheck))

#: Numbers of every kind a JSON document or a Python caller can hold: huge integers, non-finite floats,
#: booleans (not numbers here), numpy scalars.
numbers = st.one_of(
    st.integers(),
    st.integers(min_value=-(10**500), max_value=10**500),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-3.0, max_value=3.0),
    st.booleans(),
    st.floats(min_value=-3.0, max_value=3.0).map(np.float64),
)
scalars = st.one_of(st.none(), numbers, st.text(max_size=8))
json_like = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=6), st.dictionaries(st.sampled_from("tabxyz"), inner, max_size=4)
    ),
    max_leaves=12,
)


def _base_messages() -> list[dict[str, Any]]:
    """Valid messages: the canonical skeleton in metres and in millimetres, and a ZED body."""
    from app.cell.operator_sim import SimulatedOperator

    pose = SimulatedOperator(CELL, seed=0, noise=False).frame_at(0.0).joints
    conf = np.full(NUM_JOINTS, 0.9)
    zed = np.repeat(pose, 2, axis=0)[:34]
    return [
        make_message(pose, t=1.0, confidence=conf),
        make_message(pose * 1000.0, t=1.0, units="mm"),
        make_message(zed, t=1.0, format="zed34", confidence=np.full(34, 0.8)),
    ]


BASES = _base_messages()


@st.composite
def messages(draw: st.DrawFn) -> Any:
    """A valid message with up to four things changed: a field set to anything or removed, a keypoint or a
    coordinate or a confidence replaced by anything (so that most inputs reach the later checks)."""
    msg = copy.deepcopy(draw(st.sampled_from(BASES)))
    for _ in range(draw(st.integers(0, 4))):
        what = draw(st.sampled_from(["field", "drop", "joint", "coordinate", "confidence", "shift"]))
        k = draw(st.integers(0, 37))
        if what == "field":
            key = draw(
                st.sampled_from(["t", "format", "frame", "units", "joints", "confidence", "type", "body_id"])
            )
            msg[key] = draw(
                st.one_of(numbers, json_like, st.sampled_from(["canonical", "zed38", "camera", "mm"]))
            )
        elif what == "drop" and msg:
            msg.pop(draw(st.sampled_from(sorted(msg))))
        elif what == "joint" and isinstance(msg.get("joints"), list) and msg["joints"]:
            msg["joints"][k % len(msg["joints"])] = draw(st.one_of(st.none(), json_like))
        elif what == "coordinate" and isinstance(msg.get("joints"), list) and msg["joints"]:
            point = msg["joints"][k % len(msg["joints"])]
            if isinstance(point, list) and point:
                point[draw(st.integers(0, len(point) - 1))] = draw(numbers)
        elif what == "confidence" and isinstance(msg.get("confidence"), list) and msg["confidence"]:
            msg["confidence"][k % len(msg["confidence"])] = draw(
                st.one_of(st.none(), numbers, st.text(max_size=3))
            )
        elif what == "shift" and isinstance(msg.get("t"), float) and abs(msg["t"]) < 1e6:
            msg["t"] = msg["t"] + draw(st.floats(-2000.0, 2000.0))
    return msg


def _as_sent(msg: Any, how: str) -> Any:
    """The message as a Python object, as JSON text (NaN literals included) or as UTF-8 bytes."""
    if how == "object":
        return msg
    try:
        text = json.dumps(msg, default=float)
    except (TypeError, ValueError, OverflowError):
        return msg
    return text if how == "text" else text.encode()


raw_texts = st.one_of(
    st.integers(1, 30_000).map(lambda d: "[" * d + "]" * d),  # deep nesting, up to 60 kB
    st.integers(1, 30_000).map(lambda d: '{"joints": ' + "[" * d + "]" * d + "}"),
    st.integers(1, 6000).map(lambda d: '{"t": 1' + "0" * d + ', "joints": []}'),  # 10^d, past int limits
    st.text(max_size=60),
    st.binary(max_size=60),
)


def _reason_and_count(call: Any, counters: Any) -> None:
    before = dict(counters())
    try:
        out = call()
    except FrameRejected as exc:
        event(exc.reason)
        assert exc.reason in REJECT_REASONS
        after = counters()
        assert after["rejected"] == before["rejected"] + 1
        assert after[f"rejected_{exc.reason}"] == before[f"rejected_{exc.reason}"] + 1
        assert after["accepted"] == before["accepted"]
        return
    event("accepted")
    assert isinstance(out, HumanFrame)
    assert np.all(np.isfinite(out.joints)) and np.all((out.confidence >= 0) & (out.confidence <= 1))
    after = counters()
    assert (after["accepted"], after["rejected"]) == (before["accepted"] + 1, before["rejected"])


@EXAMPLES
@given(
    msg=st.one_of(messages(), messages(), messages(), json_like, raw_texts),
    how=st.sampled_from(["object", "text", "bytes"]),
    t_received=st.floats(0.0, 1e4),
)
def test_every_stream_message_is_a_frame_or_a_counted_reason(msg: Any, how: str, t_received: float) -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL), T_world_camera=np.eye(4))
    message = msg if isinstance(msg, str | bytes) else _as_sent(msg, how)
    _reason_and_count(lambda: src.push(message, t_received=t_received), lambda: src.counters)
    assert src.counters["received"] == 1


@st.composite
def poses(draw: st.DrawFn) -> Any:
    """A pose as an array or nested lists, sometimes with an entry replaced by anything; or anything."""
    pose = np.asarray(BASES[0]["joints"], dtype=np.float64) + draw(st.floats(-0.5, 0.5))
    kind = draw(st.sampled_from(["array", "lists", "mutated", "other"]))
    if kind == "array":
        return pose
    if kind == "other":
        return draw(
            st.one_of(
                json_like,
                st.lists(st.lists(numbers, max_size=4), max_size=NUM_JOINTS + 1),
                st.just(np.zeros((NUM_JOINTS, 3), dtype=bool)),
                st.just(np.full((NUM_JOINTS, 3), "1.0")),
            )
        )
    rows = pose.tolist()
    if kind == "mutated":
        rows[draw(st.integers(0, NUM_JOINTS - 1))][draw(st.integers(0, 2))] = draw(
            st.one_of(numbers, st.text(max_size=3), st.none())
        )
    return rows


@st.composite
def confidences(draw: st.DrawFn) -> Any:
    kind = draw(st.sampled_from(["none", "array", "mutated", "other"]))
    if kind == "none":
        return None
    conf = np.full(NUM_JOINTS, draw(st.floats(0.0, 1.0)))
    if kind == "array":
        return conf
    if kind == "other":
        return draw(json_like)
    values = conf.tolist()
    values[draw(st.integers(0, NUM_JOINTS - 1))] = draw(st.one_of(numbers, st.text(max_size=3), st.none()))
    return values


times = st.one_of(st.floats(0.0, 10.0), st.sampled_from([1.0, 2.0]), numbers, json_like)


@EXAMPLES
@given(first=st.tuples(times, poses(), confidences()), second=st.tuples(times, poses(), confidences()))
def test_every_validator_input_is_a_frame_or_a_counted_reason(first: Any, second: Any) -> None:
    validator = FrameValidator.for_workcell(CELL)
    for args in (first, second):  # two: the second is also checked against the first's time
        _reason_and_count(lambda args=args: validator.validate(*args), lambda: validator.counters)
    if validator.counters["accepted"]:
        assert validator.last_t is not None and math.isfinite(validator.last_t)
