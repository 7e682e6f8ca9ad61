"""Kernels for one captured graph per frame *shape* instead of per frame (issue #26, sim/rollout.py
`FRAME_GRAPHS`).

A rollout's frames differ only in the frame index k: which checkpoint row a frame starts from and
writes, which trajectory rows (k, k + 1) its contacts read, which status row its check writes, which
rows of dL/dx, dL/dF its adjoint adds and which rows of the trajectories' adjoint it accumulates into,
and (stored states) which frame's substep states it writes or reads. Here k is a device-side counter
(`ctr[0]`) that the graph itself advances, and everything indexed by k goes through a fixed *window*:

- the frame's particle state is copied from checkpoint row ctr (`rows_to_state`) and its end state into
  row ctr + 1 (`state_to_rows`);
- the contacts' rows ctr, ctr + 1 are copied into windows of 1 (active) and 2 (positions) columns
  (`frame_begin`), which the substep kernels read as frame 0; the check writes a 1-row status window
  copied in and out;
- the trajectories' adjoint rows ctr, ctr + 1 are copied into 2-column windows before the frame's
  adjoints and back after them (`adj_begin` / `adj_end`): the same atomic adds onto the same starting
  values in the same order, so bitwise what adding into the full arrays gives;
- the stored path's substep states live in one arena (frames, S + 1, P) per field; a frame runs on a
  window of S + 1 states (the replay buffer's), copied into the arena's row ctr after a stored forward
  (`window_to_arena`) and from it before the frame's adjoints (`arena_to_window`).

Only copies are added: every value the substeps compute is bitwise the per-frame path's.
"""



from types import SimpleNamespace

import warp as wp

_CACHE: dict[str, SimpleNamespace] = {}


def get_frame_kernels(dtype: str) -> SimpleNamespace:
    if dtype not in _CACHE:
        _CACHE[dtype] = _build(dtype)
    return _CACHE[dtype]


def _build(name: str) -> SimpleNamespace:  # noqa: C901
    if name == "float64":
        T, vec3, mat33 = wp.float64, wp.vec3d, wp.mat33d
    else:
        T, vec3, mat33 = wp.float32, wp.vec3f, wp.mat33f
    module = f"physinteract_framegraph_{name}"

    @wp.kernel(module=module, enable_backward=False)
    def rows_to_state(ctr: wp.array(dtype=int), off: int,
                      x2: wp.array2d(dtype=vec3), v2: wp.array2d(dtype=vec3), C2: wp.array2d(dtype=mat33),
                      F2: wp.array2d(dtype=mat33), Fv2: wp.array2d(dtype=mat33),
                      x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), C: wp.array(dtype=mat33),
                      F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33)):
        p = wp.tid()
        r = ctr[0] + off
        x[p] = x2[r, p]
        v[p] = v2[r, p]
        C[p] = C2[r, p]
        F[p] = F2[r, p]
        Fv[p] = Fv2[r, p]

    @wp.kernel(module=module, enable_backward=False)
    def state_to_rows(ctr: wp.array(dtype=int), off: int,
                      x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), C: wp.array(dtype=mat33),
                      F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33),
                      x2: wp.array2d(dtype=vec3), v2: wp.array2d(dtype=vec3), C2: wp.array2d(dtype=mat33),
                      F2: wp.array2d(dtype=mat33), Fv2: wp.array2d(dtype=mat33)):
        p = wp.tid()
        r = ctr[0] + off
        x2[r, p] = x[p]
        v2[r, p] = v[p]
        C2[r, p] = C[p]
        F2[r, p] = F[p]
        Fv2[r, p] = Fv[p]

    @wp.kernel(module=module, enable_backward=False)
    def arena_to_window(ctr: wp.array(dtype=int),
                        x3: wp.array3d(dtype=vec3), v3: wp.array3d(dtype=vec3), C3: wp.array3d(dtype=mat33),
                        F3: wp.array3d(dtype=mat33), Fv3: wp.array3d(dtype=mat33),
                        x2: wp.array2d(dtype=vec3), v2: wp.array2d(dtype=vec3), C2: wp.array2d(dtype=mat33),
                        F2: wp.array2d(dtype=mat33), Fv2: wp.array2d(dtype=mat33)):
        s, p = wp.tid()
        r = ctr[0]
        x2[s, p] = x3[r, s, p]
        v2[s, p] = v3[r, s, p]
        C2[s, p] = C3[r, s, p]
        F2[s, p] = F3[r, s, p]
        Fv2[s, p] = Fv3[r, s, p]

    @wp.kernel(module=module, enable_backward=False)
    def window_to_arena(ctr: wp.array(dtype=int),
                        x2: wp.array2d(dtype=vec3), v2: wp.array2d(dtype=vec3), C2: wp.array2d(dtype=mat33),
                        F2: wp.array2d(dtype=mat33), Fv2: wp.array2d(dtype=mat33),
                        x3: wp.array3d(dtype=vec3), v3: wp.array3d(dtype=vec3), C3: wp.array3d(dtype=mat33),
                        F3: wp.array3d(dtype=mat33), Fv3: wp.array3d(dtype=mat33)):
        s, p = wp.tid()
        r = ctr[0]
        x3[r, s, p] = x2[s, p]
        v3[r, s, p] = v2[s, p]
        C3[r, s, p] = C2[s, p]
        F3[r, s, p] = F2[s, p]
        Fv3[r, s, p] = Fv2[s, p]

    @wp.kernel(module=module, enable_backward=False)
    def frame_begin(ctr: wp.array(dtype=int),
                    pin_active: wp.array2d(dtype=wp.int32), pin_pos: wp.array2d(dtype=vec3),
                    col_active: wp.array2d(dtype=wp.int32), col_pos: wp.array2d(dtype=vec3),
                    status: wp.array2d(dtype=int),
                    w_pin_active: wp.array2d(dtype=wp.int32), w_pin_pos: wp.array2d(dtype=vec3),
                    w_col_active: wp.array2d(dtype=wp.int32), w_col_pos: wp.array2d(dtype=vec3),
                    w_status: wp.array2d(dtype=int)):
        # one thread: the contacts' rows k, k + 1 and the status row k into their windows
        k = ctr[0]
        for c in range(pin_pos.shape[0]):
            w_pin_active[c, 0] = pin_active[c, k]
            w_pin_pos[c, 0] = pin_pos[c, k]
            w_pin_pos[c, 1] = pin_pos[c, k + 1]
        for c in range(col_pos.shape[0]):
            w_col_active[c, 0] = col_active[c, k]
            w_col_pos[c, 0] = col_pos[c, k]
            w_col_pos[c, 1] = col_pos[c, k + 1]
        for j in range(status.shape[1]):
            w_status[0, j] = status[k, j]

    @wp.kernel(module=module, enable_backward=False)
    def frame_end(ctr: wp.array(dtype=int), step: int, w_status: wp.array2d(dtype=int),
                  status: wp.array2d(dtype=int)):
        k = ctr[0]
        for j in range(status.shape[1]):
            status[k, j] = w_status[0, j]
        ctr[0] = k + step

    @wp.kernel(module=module, enable_backward=False)
    def adj_begin(ctr: wp.array(dtype=int), adj_pin: wp.array2d(dtype=vec3), adj_col: wp.array2d(dtype=vec3),
                  w_pin: wp.array2d(dtype=vec3), w_col: wp.array2d(dtype=vec3)):
        k = ctr[0]
        for c in range(adj_pin.shape[0]):
            w_pin[c, 0] = adj_pin[c, k]
            w_pin[c, 1] = adj_pin[c, k + 1]
        for c in range(adj_col.shape[0]):
            w_col[c, 0] = adj_col[c, k]
            w_col[c, 1] = adj_col[c, k + 1]

    @wp.kernel(module=module, enable_backward=False)
    def adj_end(ctr: wp.array(dtype=int), step: int, w_pin: wp.array2d(dtype=vec3), w_col: wp.array2d(dtype=vec3),
                adj_pin: wp.array2d(dtype=vec3), adj_col: wp.array2d(dtype=vec3)):
        k = ctr[0]
        for c in range(adj_pin.shape[0]):
            adj_pin[c, k] = w_pin[c, 0]
            adj_pin[c, k + 1] = w_pin[c, 1]
        for c in range(adj_col.shape[0]):
            adj_col[c, k] = w_col[c, 0]
            adj_col[c, k + 1] = w_col[c, 1]
        ctr[0] = k + step

    @wp.kernel(module=module, enable_backward=False)
    def add_row_vec3(ctr: wp.array(dtype=int), off: int, g: wp.array2d(dtype=vec3), a: wp.array(dtype=vec3)):
        p = wp.tid()
        a[p] = a[p] + g[ctr[0] + off, p]       # kernels.add_vec3's arithmetic

    @wp.kernel(module=module, enable_backward=False)
    def add_row_mat33(ctr: wp.array(dtype=int), off: int, g: wp.array2d(dtype=mat33), a: wp.array(dtype=mat33)):
        p = wp.tid()
        a[p] = a[p] + g[ctr[0] + off, p]

    return SimpleNamespace(**{k: v for k, v in locals().items() if isinstance(v, wp.Kernel)})
