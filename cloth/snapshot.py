"""A copy of a session's per-frame state, put back later in place.

    start = StateSnapshot(sim.state, surface.state, layer_state)   # garments settled into a pose
    ...                                                              # frames
    start.restore()                                                  # back to that moment

What a session keeps from frame to frame is arrays in its state objects (`ClothState`,
`SurfaceState`, `LayerState` and the objects these hold); the models are shared and never
change. Restoring copies into the same arrays: the kernels' argument tuples, built once
(`ClothSim._arguments`), keep referring to them.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np


def state_arrays(state) -> Iterator[tuple[object, str, np.ndarray]]:
    """(owner, attribute, array) for every array `state` holds, and every array of the state
    objects it holds (objects of this package, e.g. `layers.SheetMoves`)."""
    for name, value in vars(state).items():
        if isinstance(value, np.ndarray):
            yield state, name, value
        elif type(value).__module__.startswith(__package__ + ".") and hasattr(value, "__dict__"):
            yield from state_arrays(value)


class StateSnapshot:
    """The arrays of some state objects as they are now (copies), to restore in place."""

    def __init__(self, *states):
        self._saved = [(owner, name, a.copy()) for s in states for owner, name, a in state_arrays(s)]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for _, _, a in self._saved)

    def onto(self, *states) -> "StateSnapshot":
        """This snapshot for other state objects built as the saved ones were (another session of
        the same outfit's models): `restore()` on it puts these values into their arrays. A
        session settled elsewhere (on a background thread, `services.cloth_service`) is so
        handed over. ValueError if the states do not hold the same arrays under the same names."""
        targets = [(owner, name, a) for s in states for owner, name, a in state_arrays(s)]
        if len(targets) != len(self._saved):
            raise ValueError(f"snapshot of {len(self._saved)} arrays onto states holding {len(targets)}")
        for (owner, name, a), (saved_owner, saved_name, saved) in zip(targets, self._saved):
            if type(owner) is not type(saved_owner) or name != saved_name:
                raise ValueError(f"snapshot's {type(saved_owner).__name__}.{saved_name} onto "
                                 f"{type(owner).__name__}.{name}")
        moved = StateSnapshot()
        moved._saved = [(owner, name, saved) for (owner, name, _), (_, _, saved) in zip(targets, self._saved)]
        return moved

    def restore(self) -> None:
        """Every saved array back, into the array it was copied from (one a step replaced with
        another shape, a scratch grown, gets a copy of the saved one)."""
        for owner, name, saved in self._saved:
            current = getattr(owner, name)
            if current.shape == saved.shape and current.dtype == saved.dtype:
                np.copyto(current, saved)
            else:
                setattr(owner, name, saved.copy())


__all__ = ["StateSnapshot", "state_arrays"]
