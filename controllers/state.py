"""Named controller state outside the runtime: design tools and tests keep a controller's state as a list
(the names are the controller's `state_names`); the compiled laws work on float64 arrays. `step_law` runs one
period of a law on either, updating the state in place."""
from __future__ import annotations

import numpy as np


def step_law(law, state, *args) -> float:
    """law(state_array, *args) -> command, with `state` a float64 array (used as it is) or a list (copied in
    and back out)."""
    if isinstance(state, np.ndarray):
        return law(state, *args)
    st = np.array(state, dtype=np.float64)
    u = law(st, *args)
    state[:] = st.tolist()
    return u
