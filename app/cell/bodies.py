"""The recorded layout of the tracked bodies of many frames, a variable number per frame.

A recording holds, per frame, every body the tracker reported with its id:

- ``skeleton`` (T, B, J, 3) float: body slot ``b`` of frame ``i``; NaN in the slots a frame does not use;
- ``body_ids`` (T, B) int: the tracker's id of each slot, ``-1`` where the slot is unused.

``B`` is the most bodies any frame held (0 when no frame held one); a frame's bodies fill its first slots,
in the tracker's order. Recordings made before several bodies were tracked hold ``skeleton`` (T, J, 3) (NaN
rows where nobody was seen): :func:`recorded_bodies` reads them as one slot, id 0 (-1 on the NaN rows).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.prediction.skeleton import NUM_JOINTS

__all__ = ["frame_bodies", "pad_bodies", "recorded_bodies"]


def pad_bodies(
    joints: Sequence[np.ndarray], body_ids: Sequence[Sequence[int]], *, dtype: type = np.float32
) -> tuple[np.ndarray, np.ndarray]:
    """The recorded layout of frames given as stacked joints (B_i*J, 3) and ids (B_i,) each.

    Returns:
        ``skeleton`` (T, B, J, 3) of ``dtype`` (NaN-padded) and ``body_ids`` (T, B) int32 (-1-padded).
    """
    if len(joints) != len(body_ids):
        raise ValueError(f"{len(joints)} frames of joints but {len(body_ids)} of body ids")
    T = len(joints)
    B = max((len(ids) for ids in body_ids), default=0)
    sk = np.full((T, B, NUM_JOINTS, 3), np.nan, dtype=dtype)
    ids_out = np.full((T, B), -1, dtype=np.int32)
    for i, (j, ids) in enumerate(zip(joints, body_ids, strict=True)):
        n = len(ids)
        if n:
            sk[i, :n] = np.asarray(j).reshape(n, NUM_JOINTS, 3)
            ids_out[i, :n] = ids
    return sk, ids_out


def recorded_bodies(
    skeleton: np.ndarray, body_ids: np.ndarray | None = None, *, dtype: type = np.float32
) -> tuple[np.ndarray, np.ndarray]:
    """``skeleton`` and ``body_ids`` in the recorded layout (see the module), checked.

    Args:
        skeleton: (T, B, J, 3) with ``body_ids`` (T, B); or the single-body layout (T, J, 3) without ids
            (one slot, id 0 where the row has a finite joint, -1 where it is all NaN).
        body_ids: The ids; ``None`` for the single-body layout, or (T, B) with ids 0 on the slots that hold
            a finite joint.

    Raises:
        ValueError: shapes that do not fit, or ids repeated within a frame.
    """
    sk = np.asarray(skeleton, dtype=dtype)
    if sk.ndim == 3:
        if sk.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"a single-body skeleton must be (T, {NUM_JOINTS}, 3), got {sk.shape}")
        sk = sk[:, None]
    if sk.ndim != 4 or sk.shape[2:] != (NUM_JOINTS, 3):
        raise ValueError(f"skeleton must be (T, B, {NUM_JOINTS}, 3) or (T, {NUM_JOINTS}, 3), got {sk.shape}")
    if body_ids is None:
        ids = np.where(np.any(np.isfinite(sk), axis=(2, 3)), 0, -1).astype(np.int32)
    else:
        ids = np.asarray(body_ids)
        if ids.shape != sk.shape[:2] or ids.dtype.kind not in "iu":
            raise ValueError(
                f"body_ids must be integers of shape {sk.shape[:2]}, got {ids.dtype} {ids.shape}"
            )
        ids = ids.astype(np.int32)
    for i in range(ids.shape[0]):
        used = ids[i][ids[i] >= 0]
        if len(np.unique(used)) != len(used):
            raise ValueError(f"frame {i} repeats a body id: {used.tolist()}")
    return sk, ids


def frame_bodies(skeleton: np.ndarray, body_ids: np.ndarray, i: int) -> tuple[np.ndarray, tuple[int, ...]]:
    """Frame ``i`` of a recording: its bodies' joints stacked (B_i*J, 3) and their ids (B_i,). A slot
    without an id, or with no finite joint, is no body."""
    ids = body_ids[i]
    keep = (ids >= 0) & np.any(np.isfinite(skeleton[i]), axis=(1, 2))
    joints = np.asarray(skeleton[i][keep], dtype=np.float64).reshape(-1, 3)
    return joints, tuple(int(b) for b in ids[keep])
