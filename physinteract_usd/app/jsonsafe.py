"""What the verbs print as JSON: no nan / inf (None instead), no numpy scalars or arrays."""

from __future__ import annotations

import numpy as np


def json_safe(o):
    """`o` with nan / inf as None, numpy scalars as Python numbers, arrays as lists; keys JSON can
    hold (str, int, float, bool) are kept, any other key (a numpy integer, a tuple) becomes its str."""
    if isinstance(o, dict):
        return {(k if type(k) in (str, int, float, bool) else str(k)): json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    if isinstance(o, np.ndarray):
        return json_safe(o.tolist())
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    return o
