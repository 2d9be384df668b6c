"""Warp kernels of the isotropic regularization in SDF-remesh (paper Sec. 3.2 (3), Algorithm 1 line 7).

The surface is a closed manifold triangle mesh stored as half-edges, with a fixed number of
vertices and faces:

* ``tri``: (3F,) int32 corners; half-edge ``h`` runs from ``tri[h]`` to ``tri[next(h)]`` inside face
  ``h // 3``, and ``tri[prev(h)]`` is the corner opposite it.
* ``twin``: (3F,) int32, the half-edge running the other way along the same edge.
* ``out_he``: (V,) int32, one half-edge leaving each vertex; ``twin[prev(h)]`` is the next one around
  the vertex, so a vertex's one-ring is walked without any adjacency list.

Every topological operation keeps V and F: an edge flip rewrites two faces; a *relocation* collapses
a short edge (freeing one vertex and two faces) and splits a long edge elsewhere with the freed
vertex and faces. Operations of one round run in parallel on an independent set: each candidate
writes its priority (a bijective hash of its half-edge, so all differ) into ``lock`` at every vertex
whose faces it reads or rewrites, with ``atomic_min``, and runs only where it holds all of them.
Relocations claim in two phases: the scarcer kind first; its winners then reserve their vertices
and the other kind claims around them.

Rings are walked at most ``max_ring`` steps; callers check beforehand that every ring closes within
that bound (:func:`ring_size`).
"""

import warp as wp


@wp.func
def he_next(h: int) -> int:
    """The next half-edge in ``h``'s face."""
    return h - h % 3 + (h % 3 + 1) % 3


@wp.func
def he_prev(h: int) -> int:
    """The previous half-edge in ``h``'s face (the one ending where ``h`` starts)."""
    return h - h % 3 + (h % 3 + 2) % 3


@wp.func
def priority(h: int, seed: int) -> int:
    """A pseudo-random priority in ``[0, 2^30)``, distinct for distinct ``h < 2^30`` (a bijection of 30 bits)."""
    x = (wp.uint32(h) ^ wp.uint32(seed)) * wp.uint32(0x5BD1E995)
    return int(x & wp.uint32(0x3FFFFFFF))


@wp.func
def owns_edge(twin: wp.array(dtype=wp.int32), h: int) -> bool:
    """Each edge is handled once, by its half-edge with the smaller index."""
    return h < twin[h]


@wp.func
def is_neighbor(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), out_he: wp.array(dtype=wp.int32),
                v: int, w: int, max_ring: int) -> bool:
    """Whether ``v`` and ``w`` share an edge."""
    h0 = out_he[v]
    h = h0
    for _ in range(max_ring):
        if tri[he_next(h)] == w:
            return True
        h = twin[he_prev(h)]
        if h == h0:
            break
    return False


@wp.func
def cos_between(u: wp.vec3, w: wp.vec3) -> float:
    """Cosine of the angle between two vectors; -1 if either is zero (a degenerate face counts as turned)."""
    d = wp.length(u) * wp.length(w)
    if d <= 0.0:
        return -1.0
    return wp.dot(u, w) / d


@wp.kernel(enable_backward=False)
def ring_size(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), out_he: wp.array(dtype=wp.int32),
              max_ring: int, valence: wp.array(dtype=wp.int32)):
    """Per vertex: the number of faces met walking its ring (its valence on a closed manifold), 0 for a
    vertex without faces, -1 when the walk does not come back within ``max_ring`` steps."""
    v = wp.tid()
    h0 = out_he[v]
    n = int(0)
    if h0 >= 0:
        h = h0
        n = int(-1)
        for k in range(max_ring):
            h = twin[he_prev(h)]
            if h == h0:
                n = k + 1
                break
    valence[v] = n


@wp.func
def outer_ok(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), g: int,
             before: wp.vec3, after: wp.vec3, min_cos: float) -> bool:
    """Whether the face across half-edge ``g`` meets a face that turns from normal ``before`` to ``after``
    at a dihedral cosine of at least ``min_cos``, or at least the one it had."""
    o = twin[g]
    p = x[tri[o]]
    outer = wp.cross(x[tri[he_next(o)]] - p, x[tri[he_prev(o)]] - p)
    return cos_between(outer, after) >= wp.min(min_cos, cos_between(outer, before))


@wp.func
def collapse_keeps_dihedrals(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32),
                             h: int, m: wp.vec3, min_cos: float, max_ring: int) -> bool:
    """Whether collapsing ``a -> b`` (half-edge ``h``) into ``m`` leaves every edge at the merged vertex
    (spokes, and the ring's outer edges) with a dihedral cosine of at least ``min_cos``, or at least
    the one it had.

    The merged vertex's faces are ``a``'s from the one after ``(a, b, c)`` to the one before
    ``(b, a, d)``, then ``b``'s likewise; at the two junctions (across ``m c`` and ``m d``) faces meet
    that were not adjacent before.
    """
    t = twin[h]
    first = wp.vec3(0.0)
    last_after = wp.vec3(0.0)
    last_before = wp.vec3(0.0)
    count = int(0)
    for side in range(2):
        g = twin[he_prev(wp.where(side == 0, h, t))]
        stop = he_next(wp.where(side == 0, t, h))
        j = int(0)
        for _ in range(max_ring):
            if g == stop:
                break
            p = x[tri[g]]
            w = x[tri[he_next(g)]]
            u = x[tri[he_prev(g)]]
            before = wp.cross(w - p, u - p)
            after = wp.cross(w - m, u - m)
            if not outer_ok(x, tri, twin, he_next(g), before, after, min_cos):
                return False
            if count == 0:
                first = after
            else:
                had = float(1.0)
                if j > 0:
                    had = cos_between(last_before, before)
                if cos_between(last_after, after) < wp.min(min_cos, had):
                    return False
            last_after = after
            last_before = before
            count += 1
            j += 1
            g = twin[he_prev(g)]
    return cos_between(last_after, first) >= min_cos


@wp.kernel(enable_backward=False)
def mark_relocations(
    x: wp.array(dtype=wp.vec3),
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    valence: wp.array(dtype=wp.int32),
    short_len: float,
    long_len: float,
    max_valence: int,
    min_cos: float,
    flat_cos: float,
    max_ring: int,
    kind: wp.array(dtype=wp.int32),
    num_kind: wp.array(dtype=wp.int32),
):
    """Per half-edge: ``kind`` 1 for an edge to collapse, 2 for one to split, else 0; ``num_kind[k - 1]``
    counts them (zeroed first).

    Collapse ``a -> b`` into its midpoint ``m`` when shorter than ``short_len`` and: the link condition
    holds (``a`` and ``b`` share exactly the two neighbours ``c``, ``d`` opposite the edge, so the
    topology is kept); ``c`` and ``d`` keep three edges at least; ``m`` gets at most ``max_valence``
    edges, none longer than ``long_len`` unless it was already; the faces around ``a`` and ``b`` are
    flat enough (``|sum n_f| >= flat_cos * sum |n_f|``, so tips are not collapsed away); no remaining
    face turns by more than ``acos(min_cos)`` unless it then agrees that well with their mean normal;
    and no edge at ``m`` gets a dihedral cosine below ``min_cos`` and below the one it had. Split
    when longer than ``long_len`` (unless ``c`` or ``d`` would get more edges than a ring walk follows).
    """
    h = wp.tid()
    kind[h] = 0
    if not owns_edge(twin, h):
        return
    t = twin[h]
    a = tri[h]
    b = tri[he_next(h)]
    c = tri[he_prev(h)]
    d = tri[he_prev(t)]
    pa = x[a]
    pb = x[b]
    length = wp.length(pb - pa)
    if length > long_len:
        # a split adds an edge at c and d: never past what a ring walk can follow
        if valence[c] < max_ring - 1 and valence[d] < max_ring - 1:
            kind[h] = 2
            wp.atomic_add(num_kind, 1, 1)
        return
    if length >= short_len:
        return
    if valence[c] <= 3 or valence[d] <= 3 or valence[a] + valence[b] - 4 > max_valence:
        return
    m = 0.5 * (pa + pb)
    normal = wp.vec3(0.0)
    total = float(0.0)
    for side in range(2):
        v = wp.where(side == 0, a, b)
        g0 = out_he[v]
        g = g0
        for _ in range(max_ring):
            cr = wp.cross(x[tri[he_next(g)]] - x[v], x[tri[he_prev(g)]] - x[v])
            normal += cr
            total += wp.length(cr)
            g = twin[he_prev(g)]
            if g == g0:
                break
    if wp.length(normal) < flat_cos * total:
        return
    common = int(0)
    for side in range(2):
        v = wp.where(side == 0, a, b)
        other = wp.where(side == 0, b, a)
        pv = x[v]
        g0 = out_he[v]
        g = g0
        for _ in range(max_ring):
            w = tri[he_next(g)]
            u = tri[he_prev(g)]
            if w != other:
                if wp.length(x[w] - m) > wp.max(long_len, wp.length(x[w] - pv)):
                    return
                if side == 0 and is_neighbor(tri, twin, out_he, b, w, max_ring):
                    common += 1
            if w != other and u != other:
                before = wp.cross(x[w] - pv, x[u] - pv)
                after = wp.cross(x[w] - m, x[u] - m)
                if cos_between(before, after) < min_cos and cos_between(normal, after) < min_cos:
                    return
            g = twin[he_prev(g)]
            if g == g0:
                break
    if common != 2 or not collapse_keeps_dihedrals(x, tri, twin, h, m, min_cos, max_ring):
        return
    kind[h] = 1
    wp.atomic_add(num_kind, 0, 1)


@wp.func
def claimed_kind(num_kind: wp.array(dtype=wp.int32), phase: int) -> int:
    """The kind that claims vertices in ``phase``: 0 the scarcer of collapses (1) and splits (2), 1 the other.

    A split is applied only paired with a collapse, so the scarcer kind goes first and the other
    fills in around it; otherwise the abundant kind (a collapse claims a dozen vertices) would
    crowd it out.
    """
    scarce = wp.where(num_kind[0] <= num_kind[1], 1, 2)
    return wp.where(phase == 0, scarce, 3 - scarce)


@wp.func
def visit_relocation(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), lock: wp.array(dtype=wp.int32),
                     h: int, k: int, p: int, mode: int, max_ring: int) -> int:
    """Over the vertices a relocation reads or rewrites (split: ``a, b, c, d``; collapse: ``a``, ``b`` and
    all their neighbours): claim them (``mode`` 0, ``atomic_min`` of ``p``), check that ``p`` holds
    all of them (1; returns 0 if not), or reserve them (2, write -1, below every priority)."""
    held = int(1)
    if k == 2:
        for j in range(4):
            v = tri[h]
            if j == 1:
                v = tri[he_next(h)]
            elif j == 2:
                v = tri[he_prev(h)]
            elif j == 3:
                v = tri[he_prev(twin[h])]
            if mode == 0:
                wp.atomic_min(lock, v, p)
            elif mode == 1:
                if lock[v] != p:
                    held = 0
            else:
                lock[v] = -1
        return held
    for side in range(2):
        g0 = wp.where(side == 0, h, twin[h])
        g = g0
        for _ in range(max_ring):
            v = tri[he_next(g)]
            if mode == 0:
                wp.atomic_min(lock, v, p)
            elif mode == 1:
                if lock[v] != p:
                    held = 0
            else:
                lock[v] = -1
            g = twin[he_prev(g)]
            if g == g0:
                break
    return held


@wp.kernel(enable_backward=False)
def claim_relocations(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
                      num_kind: wp.array(dtype=wp.int32), phase: int, seed: int, max_ring: int,
                      lock: wp.array(dtype=wp.int32)):
    """Per candidate of the kind claiming in ``phase``: claim its vertices with its priority."""
    h = wp.tid()
    k = kind[h]
    if k != 0 and k == claimed_kind(num_kind, phase):
        visit_relocation(tri, twin, lock, h, k, priority(h, seed), 0, max_ring)


@wp.kernel(enable_backward=False)
def relocation_winners(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
                       num_kind: wp.array(dtype=wp.int32), phase: int, seed: int, max_ring: int,
                       lock: wp.array(dtype=wp.int32), collapse: wp.array(dtype=wp.int32),
                       split: wp.array(dtype=wp.int32)):
    """Per candidate of the kind claiming in ``phase``: 1 in ``collapse`` / ``split`` where it holds every
    vertex it claimed (both zeroed in phase 0)."""
    h = wp.tid()
    if phase == 0:
        collapse[h] = 0
        split[h] = 0
    k = kind[h]
    if k == 0 or k != claimed_kind(num_kind, phase):
        return
    if visit_relocation(tri, twin, lock, h, k, priority(h, seed), 1, max_ring) != 0:
        if k == 1:
            collapse[h] = 1
        else:
            split[h] = 1


@wp.kernel(enable_backward=False)
def reserve_relocations(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32),
                        collapse: wp.array(dtype=wp.int32), split: wp.array(dtype=wp.int32), max_ring: int,
                        lock: wp.array(dtype=wp.int32)):
    """Per phase-0 winner: mark its vertices taken (``lock`` was reset), so phase 1 builds around it."""
    h = wp.tid()
    if collapse[h] != 0:
        visit_relocation(tri, twin, lock, h, 1, 0, 2, max_ring)
    elif split[h] != 0:
        visit_relocation(tri, twin, lock, h, 2, 0, 2, max_ring)


@wp.kernel(enable_backward=False)
def compact(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32),
            count: wp.array(dtype=wp.int32)):
    """Per entry: write the indices of set ``flags`` to ``out[offsets[i]]`` (``offsets`` is their
    exclusive scan); the last entry writes how many there are to ``count[0]``."""
    i = wp.tid()
    if flags[i] != 0:
        out[offsets[i]] = i
    if i == flags.shape[0] - 1:
        count[0] = offsets[i] + flags[i]


@wp.kernel(enable_backward=False)
def apply_relocations(
    x: wp.array(dtype=wp.vec3),
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    collapses: wp.array(dtype=wp.int32),
    num_collapses: wp.array(dtype=wp.int32),
    splits: wp.array(dtype=wp.int32),
    num_splits: wp.array(dtype=wp.int32),
    max_ring: int,
):
    """Pair ``i``: collapse edge ``collapses[i]`` and split edge ``splits[i]`` with the vertex and the two
    faces the collapse freed, for ``i`` below the smaller count (V and F stay the same)."""
    i = wp.tid()
    if i >= wp.min(num_collapses[0], num_splits[0]):
        return
    # collapse a -> b (faces f0 = (a, b, c), f1 = (b, a, d)): b's corners become a, a moves to the midpoint
    h = collapses[i]
    t = twin[h]
    a = tri[h]
    b = tri[he_next(h)]
    c = tri[he_prev(h)]
    d = tri[he_prev(t)]
    o_bc = twin[he_next(h)]
    o_ca = twin[he_prev(h)]
    o_ad = twin[he_next(t)]
    o_db = twin[he_prev(t)]
    g0 = out_he[b]
    g = g0
    for _ in range(max_ring):
        nxt = twin[he_prev(g)]
        tri[g] = a
        g = nxt
        if g == g0:
            break
    twin[o_bc] = o_ca
    twin[o_ca] = o_bc
    twin[o_ad] = o_db
    twin[o_db] = o_ad
    out_he[a] = o_ca
    out_he[c] = o_bc
    out_he[d] = o_ad
    x[a] = 0.5 * (x[a] + x[b])
    m = b
    n0 = 3 * (h // 3)
    n1 = 3 * (t // 3)
    # split a2 -> b2 (faces g0 = (a2, b2, c2), g1 = (b2, a2, d2)) at its midpoint m:
    # g0 = (a2, m, c2), n0 = (m, b2, c2), g1 = (b2, m, d2), n1 = (m, a2, d2)
    s = splits[i]
    u = twin[s]
    a2 = tri[s]
    b2 = tri[he_next(s)]
    c2 = tri[he_prev(s)]
    d2 = tri[he_prev(u)]
    q_bc = twin[he_next(s)]
    q_ca = twin[he_prev(s)]
    q_ad = twin[he_next(u)]
    q_db = twin[he_prev(u)]
    G0 = 3 * (s // 3)
    G1 = 3 * (u // 3)
    tri[G0] = a2
    tri[G0 + 1] = m
    tri[G0 + 2] = c2
    tri[n0] = m
    tri[n0 + 1] = b2
    tri[n0 + 2] = c2
    tri[G1] = b2
    tri[G1 + 1] = m
    tri[G1 + 2] = d2
    tri[n1] = m
    tri[n1 + 1] = a2
    tri[n1 + 2] = d2
    twin[G0] = n1
    twin[n1] = G0
    twin[G0 + 1] = n0 + 2
    twin[n0 + 2] = G0 + 1
    twin[G0 + 2] = q_ca
    twin[q_ca] = G0 + 2
    twin[n0] = G1
    twin[G1] = n0
    twin[n0 + 1] = q_bc
    twin[q_bc] = n0 + 1
    twin[G1 + 1] = n1 + 2
    twin[n1 + 2] = G1 + 1
    twin[G1 + 2] = q_db
    twin[q_db] = G1 + 2
    twin[n1 + 1] = q_ad
    twin[q_ad] = n1 + 1
    out_he[m] = n0
    out_he[a2] = G0
    out_he[b2] = G1
    out_he[c2] = G0 + 2
    out_he[d2] = G1 + 2
    x[m] = 0.5 * (x[a2] + x[b2])


@wp.kernel(enable_backward=False)
def mark_flips(
    x: wp.array(dtype=wp.vec3),
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    valence: wp.array(dtype=wp.int32),
    min_cos: float,
    flat_cos: float,
    max_ring: int,
    seed: int,
    candidate: wp.array(dtype=wp.int32),
    lock: wp.array(dtype=wp.int32),
):
    """Per half-edge: ``candidate`` 1 where flipping edge ``a b`` to ``c d`` lowers the valence deviation
    ``sum |valence - 6|`` of ``a, b, c, d``, keeps every valence >= 3 and does not duplicate an edge,
    where the edge is no crease (its faces meet at a cosine of at least ``flat_cos``), and where the two
    new faces turn less than ``acos(min_cos)`` from each other and from the old faces' mean normal
    and meet the four faces around them at a dihedral cosine of at least ``min_cos`` (or the one they
    had); candidates claim ``a, b, c, d``."""
    h = wp.tid()
    candidate[h] = 0
    if not owns_edge(twin, h):
        return
    t = twin[h]
    a = tri[h]
    b = tri[he_next(h)]
    c = tri[he_prev(h)]
    d = tri[he_prev(t)]
    if c == d or valence[a] <= 3 or valence[b] <= 3:
        return
    before = wp.abs(valence[a] - 6) + wp.abs(valence[b] - 6) + wp.abs(valence[c] - 6) + wp.abs(valence[d] - 6)
    after = wp.abs(valence[a] - 7) + wp.abs(valence[b] - 7) + wp.abs(valence[c] - 5) + wp.abs(valence[d] - 5)
    if after >= before:
        return
    pa = x[a]
    pb = x[b]
    pc = x[c]
    pd = x[d]
    n0 = wp.cross(pb - pa, pc - pa)
    n1 = wp.cross(pa - pb, pd - pb)
    m0 = wp.cross(pd - pa, pc - pa)
    m1 = wp.cross(pc - pb, pd - pb)
    mean = wp.vec3(0.0)
    if wp.length(n0) > 0.0 and wp.length(n1) > 0.0:
        mean = wp.normalize(n0) + wp.normalize(n1)
    if cos_between(n0, n1) < flat_cos:
        return
    if cos_between(m0, m1) < min_cos or cos_between(m0, mean) < min_cos or cos_between(m1, mean) < min_cos:
        return
    if is_neighbor(tri, twin, out_he, c, d, max_ring):
        return
    # after the flip, b c and d b lie in (b, c, d), c a and a d in (a, d, c)
    if not outer_ok(x, tri, twin, he_next(h), n0, m1, min_cos):
        return
    if not outer_ok(x, tri, twin, he_prev(h), n0, m0, min_cos):
        return
    if not outer_ok(x, tri, twin, he_next(t), n1, m0, min_cos):
        return
    if not outer_ok(x, tri, twin, he_prev(t), n1, m1, min_cos):
        return
    candidate[h] = 1
    p = priority(h, seed)
    wp.atomic_min(lock, a, p)
    wp.atomic_min(lock, b, p)
    wp.atomic_min(lock, c, p)
    wp.atomic_min(lock, d, p)


@wp.kernel(enable_backward=False)
def apply_flips(
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    candidate: wp.array(dtype=wp.int32),
    lock: wp.array(dtype=wp.int32),
    seed: int,
):
    """Per candidate holding its four vertices: faces ``(a, b, c), (b, a, d)`` become ``(a, d, c), (b, c, d)``."""
    h = wp.tid()
    if candidate[h] == 0:
        return
    t = twin[h]
    a = tri[h]
    b = tri[he_next(h)]
    c = tri[he_prev(h)]
    d = tri[he_prev(t)]
    p = priority(h, seed)
    if lock[a] != p or lock[b] != p or lock[c] != p or lock[d] != p:
        return
    o_bc = twin[he_next(h)]
    o_ca = twin[he_prev(h)]
    o_ad = twin[he_next(t)]
    o_db = twin[he_prev(t)]
    F0 = 3 * (h // 3)
    F1 = 3 * (t // 3)
    tri[F0] = a
    tri[F0 + 1] = d
    tri[F0 + 2] = c
    tri[F1] = b
    tri[F1 + 1] = c
    tri[F1 + 2] = d
    twin[F0] = o_ad
    twin[o_ad] = F0
    twin[F0 + 1] = F1 + 1
    twin[F1 + 1] = F0 + 1
    twin[F0 + 2] = o_ca
    twin[o_ca] = F0 + 2
    twin[F1] = o_bc
    twin[o_bc] = F1
    twin[F1 + 2] = o_db
    twin[o_db] = F1 + 2
    out_he[a] = F0
    out_he[b] = F1
    out_he[c] = F0 + 2
    out_he[d] = F1 + 2


@wp.func
def phong_point(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), normals: wp.array(dtype=wp.vec3),
                face: int, u: float, v: float, flat_cos: float) -> wp.vec3:
    """The point at barycentrics ``(u, v, 1 - u - v)`` of a face, lifted onto the surface's Phong
    tessellation (Boubekeur and Alexa 2008, shape factor 3/4): the flat point projected onto the
    tangent planes of the three corners (unit vertex ``normals``), blended with the same weights.

    Vertices of a mesh lie on the surface it samples and its faces are chords under it; the lifted
    point lies on a smooth interpolation through the vertices, so a re-tessellation projected there
    neither flattens nor (after rescaling the area) inflates the shape. Where two corner normals
    differ by more than ``acos(flat_cos)`` (a crease) the flat point is kept.
    """
    i0 = indices[3 * face]
    i1 = indices[3 * face + 1]
    i2 = indices[3 * face + 2]
    w = 1.0 - u - v
    q = u * points[i0] + v * points[i1] + w * points[i2]
    n0 = normals[i0]
    n1 = normals[i1]
    n2 = normals[i2]
    if wp.dot(n0, n1) < flat_cos or wp.dot(n1, n2) < flat_cos or wp.dot(n2, n0) < flat_cos:
        return q
    t0 = q - wp.dot(q - points[i0], n0) * n0
    t1 = q - wp.dot(q - points[i1], n1) * n1
    t2 = q - wp.dot(q - points[i2], n2) * n2
    return 0.25 * q + 0.75 * (u * t0 + v * t1 + w * t2)


@wp.func
def surface_target(surface: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                   normals: wp.array(dtype=wp.vec3), p: wp.vec3, n: wp.vec3, max_dist: float, flat_cos: float,
                   ) -> wp.vec4:
    """The Phong-lifted closest point of ``surface`` to ``p`` within ``max_dist`` (xyz) and 1 (w), or w = 0
    when there is none or it lies on a face facing away from ``n`` (the other side of a thin part)."""
    hit = wp.mesh_query_point_no_sign(surface, p, max_dist)
    if hit.result:
        if wp.dot(wp.mesh_eval_face_normal(surface, hit.face), n) > 0.0:
            q = phong_point(points, indices, normals, hit.face, hit.u, hit.v, flat_cos)
            return wp.vec4(q[0], q[1], q[2], 1.0)
    return wp.vec4(0.0)


@wp.func
def ring_normal(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32),
                h0: int, max_ring: int) -> wp.vec4:
    """Sum of the cross products of the faces around the vertex of half-edge ``h0`` (xyz) and the sum of their
    lengths (w)."""
    p = x[tri[h0]]
    n = wp.vec3(0.0)
    w = float(0.0)
    h = h0
    for _ in range(max_ring):
        cr = wp.cross(x[tri[he_next(h)]] - p, x[tri[he_prev(h)]] - p)
        n += cr
        w += wp.length(cr)
        h = twin[he_prev(h)]
        if h == h0:
            break
    return wp.vec4(n[0], n[1], n[2], w)


@wp.kernel(enable_backward=False)
def tangential_relax(
    surface: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    max_dist: float,
    min_cos: float,
    flat_cos: float,
    max_ring: int,
    out: wp.array(dtype=wp.vec3),
    moved: wp.array(dtype=wp.float64),
):
    """Per vertex: move to the area-weighted centroid of its faces' centroids, tangentially (the normal
    component of the move removed), then onto the Phong-lifted closest point of ``surface`` (a
    ``wp.Mesh`` wound the same way, on ``points`` and ``indices``, with unit vertex ``normals``; see
    :func:`phong_point`) within ``max_dist``; write the result to ``out``.

    A feature vertex (its faces' normals spread: ``|sum n_f| < flat_cos * sum |n_f|``) stays, or a tip
    or crease would be smoothed away. The move is halved up to twice, and dropped, if a face of the
    vertex would turn more than ``acos(min_cos)`` with its neighbours held fixed (unless it then
    agrees that well with the vertex normal: a near-degenerate face may turn freely into shape), or
    if the closest point lies on a face facing away from the vertex normal (the other side of a thin
    part). Writes the distance moved to ``moved[v]`` (summed afterwards in a fixed order).
    """
    v = wp.tid()
    p = x[v]
    out[v] = p
    moved[v] = wp.float64(0.0)
    h0 = out_he[v]
    if h0 < 0:
        return
    g = wp.vec3(0.0)
    w = float(0.0)
    h = h0
    for _ in range(max_ring):
        q = x[tri[he_next(h)]]
        r = x[tri[he_prev(h)]]
        area = wp.length(wp.cross(q - p, r - p))
        g += area * (p + q + r) / 3.0
        w += area
        h = twin[he_prev(h)]
        if h == h0:
            break
    ring = ring_normal(x, tri, twin, h0, max_ring)
    n = wp.vec3(ring[0], ring[1], ring[2])
    if w <= 0.0 or wp.length(n) < flat_cos * ring[3]:
        return
    n = wp.normalize(n)
    move = g / w - p
    move = move - wp.dot(move, n) * n
    step = float(1.0)
    for _attempt in range(3):
        found = surface_target(surface, points, indices, normals, p + step * move, n, max_dist, flat_cos)
        target = wp.vec3(found[0], found[1], found[2])
        ok = int(found[3])
        if ok != 0:
            h = h0
            for _ in range(max_ring):
                q = x[tri[he_next(h)]]
                r = x[tri[he_prev(h)]]
                after = wp.cross(q - target, r - target)
                if cos_between(wp.cross(q - p, r - p), after) < min_cos and cos_between(n, after) < min_cos:
                    ok = 0
                h = twin[he_prev(h)]
                if h == h0:
                    break
        if ok != 0:
            out[v] = target
            moved[v] = wp.float64(wp.length(target - p))
            return
        step = 0.5 * step


@wp.kernel(enable_backward=False)
def project_onto(
    surface: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri: wp.array(dtype=wp.int32),
    twin: wp.array(dtype=wp.int32),
    out_he: wp.array(dtype=wp.int32),
    max_dist: float,
    flat_cos: float,
    max_ring: int,
    out: wp.array(dtype=wp.vec3),
):
    """Per vertex: onto the Phong-lifted closest point of ``surface`` (as :func:`tangential_relax`, without
    the tangential move), so that vertices the last relocations left at edge midpoints lie on the
    surface too; vertices whose closest point faces away stay."""
    v = wp.tid()
    p = x[v]
    out[v] = p
    h0 = out_he[v]
    if h0 < 0:
        return
    ring = ring_normal(x, tri, twin, h0, max_ring)
    n = wp.vec3(ring[0], ring[1], ring[2])
    if wp.length(n) <= 0.0:
        return
    found = surface_target(surface, points, indices, normals, p, wp.normalize(n), max_dist, flat_cos)
    if found[3] != 0.0:
        out[v] = wp.vec3(found[0], found[1], found[2])


@wp.kernel(enable_backward=False)
def mark_sharpened_edges(x_old: wp.array(dtype=wp.vec3), x_new: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32),
                         twin: wp.array(dtype=wp.int32), min_cos: float, revert: wp.array(dtype=wp.int32)):
    """Per edge whose faces the relaxation bent to a dihedral cosine below ``min_cos`` and below the one
    they had (a fold, or a new crease: neighbours moved at once, each move checked with the others
    held): flag the four vertices of its two faces in ``revert``."""
    h = wp.tid()
    if not owns_edge(twin, h):
        return
    t = twin[h]
    a = tri[h]
    b = tri[he_next(h)]
    c = tri[he_prev(h)]
    d = tri[he_prev(t)]
    before = cos_between(wp.cross(x_old[b] - x_old[a], x_old[c] - x_old[a]),
                         wp.cross(x_old[a] - x_old[b], x_old[d] - x_old[b]))
    after = cos_between(wp.cross(x_new[b] - x_new[a], x_new[c] - x_new[a]),
                        wp.cross(x_new[a] - x_new[b], x_new[d] - x_new[b]))
    if after < wp.min(min_cos, before):
        revert[a] = 1
        revert[b] = 1
        revert[c] = 1
        revert[d] = 1


@wp.kernel(enable_backward=False)
def revert_vertices(x_old: wp.array(dtype=wp.vec3), revert: wp.array(dtype=wp.int32), x_new: wp.array(dtype=wp.vec3)):
    """Per flagged vertex: back to its position before the sweep; clears the flag."""
    v = wp.tid()
    if revert[v] != 0:
        x_new[v] = x_old[v]
        revert[v] = 0


@wp.kernel(enable_backward=False)
def check_halfedges(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), errors: wp.array(dtype=wp.int32)):
    """Per half-edge: count in ``errors[0]`` the ones whose twin is not an opposite half-edge of the same edge
    pointing back (``twin[twin[h]] == h``, reversed endpoints): with none, every edge has exactly two
    consistently wound faces."""
    h = wp.tid()
    t = twin[h]
    ok = t >= 0 and t < twin.shape[0] and t != h
    if ok:
        ok = twin[t] == h and tri[t] == tri[he_next(h)] and tri[he_next(t)] == tri[h]
    if not ok:
        wp.atomic_add(errors, 0, 1)


@wp.kernel(enable_backward=False)
def check_rings(valence: wp.array(dtype=wp.int32), errors: wp.array(dtype=wp.int32)):
    """Per vertex: count in ``errors[1]`` the ones whose ring walk failed (no face, or no return within the
    walk bound), and add the faces met to ``errors[2]``: on a vertex-manifold surface the walks meet every
    half-edge once (``3 F`` in all); a vertex with two fans of faces meets only one of them."""
    v = wp.tid()
    n = valence[v]
    if n <= 0:
        wp.atomic_add(errors, 1, 1)
    else:
        wp.atomic_add(errors, 2, n)


@wp.kernel(enable_backward=False)
def face_measures(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), sliver: float, tiny: float,
                  area: wp.array(dtype=wp.float64), volume: wp.array(dtype=wp.float64),
                  centroid: wp.array(dtype=wp.vec3d), bad: wp.array(dtype=wp.int32)):
    """Per face: its area, its signed volume about the origin and its area-weighted centroid (float64; zero for
    a face with a non-finite corner), summed afterwards in a fixed order (:func:`vnc_warp._reduce.ordered_sum`);
    count in ``bad[0]`` faces with a non-finite corner and in ``bad[1]`` slivers (``2 area <= sliver * sum of
    squared edge lengths`` or ``2 area <= tiny``), the faces Warp's closest-point queries skip (``bad`` zeroed
    first)."""
    f = wp.tid()
    area[f] = wp.float64(0.0)
    volume[f] = wp.float64(0.0)
    centroid[f] = wp.vec3d(wp.float64(0.0))
    a = x[tri[3 * f]]
    b = x[tri[3 * f + 1]]
    c = x[tri[3 * f + 2]]
    s = a[0] + a[1] + a[2] + b[0] + b[1] + b[2] + c[0] + c[1] + c[2]
    if not wp.isfinite(s):
        wp.atomic_add(bad, 0, 1)
        return
    ad = wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))
    bd = wp.vec3d(wp.float64(b[0]), wp.float64(b[1]), wp.float64(b[2]))
    cd = wp.vec3d(wp.float64(c[0]), wp.float64(c[1]), wp.float64(c[2]))
    cr = wp.cross(bd - ad, cd - ad)
    area2 = wp.length(cr)
    sq = wp.length_sq(bd - ad) + wp.length_sq(cd - ad) + wp.length_sq(cd - bd)
    if area2 <= wp.float64(sliver) * sq or area2 <= wp.float64(tiny):
        wp.atomic_add(bad, 1, 1)
    area[f] = wp.float64(0.5) * area2
    volume[f] = wp.dot(ad, wp.cross(bd, cd)) / wp.float64(6.0)
    centroid[f] = (wp.float64(0.5) * area2 / wp.float64(3.0)) * (ad + bd + cd)


@wp.kernel(enable_backward=False)
def owned_edges(twin: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """Per half-edge: 1 if it stands for its edge (:func:`owns_edge`), else 0."""
    h = wp.tid()
    flags[h] = wp.where(owns_edge(twin, h), 1, 0)


@wp.kernel(enable_backward=False)
def edge_topology(tri: wp.array(dtype=wp.int32), twin: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                  edges: wp.array(dtype=wp.vec2i), interior: wp.array(dtype=wp.vec4i)):
    """Per owning half-edge ``a -> b`` (edge ``offsets[h]``): the edge's sorted endpoints, and ``(a, b, c0, c1)``
    with face ``(a, b, c0)`` running ``a -> b`` and face ``(b, a, c1)`` running ``b -> a``, the layout of
    :class:`vnc_warp.mesh.EdgeTopology`."""
    h = wp.tid()
    if not owns_edge(twin, h):
        return
    i = offsets[h]
    a = tri[h]
    b = tri[he_next(h)]
    edges[i] = wp.vec2i(wp.min(a, b), wp.max(a, b))
    interior[i] = wp.vec4i(a, b, tri[he_prev(h)], tri[he_prev(twin[h])])


@wp.kernel(enable_backward=False)
def scale_about(x: wp.array(dtype=wp.vec3), centre: wp.vec3, factor: float):
    """Per vertex: ``x <- centre + factor (x - centre)``."""
    v = wp.tid()
    x[v] = centre + factor * (x[v] - centre)


@wp.kernel(enable_backward=False)
def last_outgoing(tri: wp.array(dtype=wp.int32), out_he: wp.array(dtype=wp.int32)):
    """Per half-edge: max it into ``out_he`` of the vertex it leaves (``out_he`` set to -1 first): a canonical
    choice of each vertex's outgoing half-edge, so a surface rebuilt from its faces walks its rings the same way."""
    h = wp.tid()
    wp.atomic_max(out_he, tri[h], h)
