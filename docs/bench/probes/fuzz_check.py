"""The independent float64 checker of `fuzz.py` (numpy only, no simulator code): per frame,
edge-triangle self-crossings, free vertices inside or nearer an obstacle than the thickness less
0.1 mm (analytic signed distances from its own pose of each obstacle's motion; winding numbers
for meshes), cloth edge points inside an obstacle, obstacle mesh edges through the cloth's
triangles, NaN, edge strain, pins' clearance."""
import math
import numpy as np


# ---------------- quaternions (x, y, z, w), own implementation
def qmat(q):
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def axis_angle_mat(w, ang):
    n = np.linalg.norm(w)
    if n == 0 or ang == 0:
        return np.eye(3)
    k = np.asarray(w, float) / n
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def slerp(a, b, s):
    a = np.asarray(a, float); b = np.asarray(b, float)
    a = a / np.linalg.norm(a); b = b / np.linalg.norm(b)
    d = a @ b
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        q = a + s * (b - a); return q / np.linalg.norm(q)
    th = math.acos(min(d, 1.0))
    return (math.sin((1 - s) * th) * a + math.sin(s * th) * b) / math.sin(th)


def pose(spec, t):
    """spec: dict(pos, rot (quat), lin, ang, start, ramp, path=(times, offs, quats)|None).
    returns centre c (3,), rotation matrix R (3,3)."""
    s = max(t - spec.get("start", 0.0), 0.0); ramp = spec.get("ramp", 0.0)
    tau = s * s / (2 * ramp) if (ramp > 0 and s < ramp) else s - 0.5 * ramp
    c = np.asarray(spec["pos"], float) + np.asarray(spec.get("lin", (0, 0, 0)), float) * tau
    R = qmat(spec.get("rot", (0, 0, 0, 1)))
    p = spec.get("path")
    if p is not None:
        ts, offs, qs = np.asarray(p[0], float), np.asarray(p[1], float), np.asarray(p[2], float)
        if t <= ts[0]:
            off, q = offs[0], qs[0]
        elif t >= ts[-1]:
            off, q = offs[-1], qs[-1]
        else:
            k = int(np.searchsorted(ts, t, side="right") - 1); u = (t - ts[k]) / (ts[k + 1] - ts[k])
            off = offs[k] * (1 - u) + offs[k + 1] * u; q = slerp(qs[k], qs[k + 1], u)
        c = c + off; R = qmat(q) @ R
    w = np.asarray(spec.get("ang", (0, 0, 0)), float)
    if np.any(w):
        R = axis_angle_mat(w, np.linalg.norm(w) * tau) @ R
    return c, R


# ---------------- geometry
def edges_from(tris):
    e = np.sort(np.vstack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def orient(a, b, c, d):
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))


def seg_tri_pairs(P, E, Q, T, skip_shared):
    """list of (edge idx, tri idx) where segment P[E] strictly crosses triangle Q[T]."""
    A, B, C = Q[T[:, 0]], Q[T[:, 1]], Q[T[:, 2]]
    tlo = np.minimum(np.minimum(A, B), C); thi = np.maximum(np.maximum(A, B), C)
    E0, E1 = P[E[:, 0]], P[E[:, 1]]
    elo = np.minimum(E0, E1); ehi = np.maximum(E0, E1)
    out = []
    for i0 in range(0, len(E), 200):
        sl = slice(i0, i0 + 200)
        ov = np.all((elo[sl, None, :] <= thi[None]) & (ehi[sl, None, :] >= tlo[None]), axis=2)
        ei, ti = np.nonzero(ov)
        ei = ei + i0
        if skip_shared and len(ei):
            e, t = E[ei], T[ti]
            sh = (e[:, :1] == t).any(1) | (e[:, 1:] == t).any(1)
            ei, ti = ei[~sh], ti[~sh]
        if not len(ei):
            continue
        p, q = E0[ei], E1[ei]; a, b, c = A[ti], B[ti], C[ti]
        s1 = orient(p, a, b, c); s2 = orient(q, a, b, c)
        o1 = orient(p, q, a, b); o2 = orient(p, q, b, c); o3 = orient(p, q, c, a)
        hit = (s1 * s2 < 0) & (((o1 > 0) & (o2 > 0) & (o3 > 0)) | ((o1 < 0) & (o2 < 0) & (o3 < 0)))
        for k in np.flatnonzero(hit):
            out.append((int(ei[k]), int(ti[k])))
    return out


def point_tri_dist(p, a, b, c):
    """vectorised closest distance (Ericson), all arrays (M,3)."""
    ab = b - a; ac = c - a; ap = p - a
    d1 = np.einsum("ij,ij->i", ab, ap); d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b; d3 = np.einsum("ij,ij->i", ab, bp); d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c; d5 = np.einsum("ij,ij->i", ab, cp); d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4; vb = d5 * d2 - d1 * d6; vc = d1 * d4 - d3 * d2
    res = np.empty_like(p)
    done = np.zeros(len(p), bool)

    def put(m, v):
        nonlocal done
        m = m & ~done; res[m] = v[m]; done |= m
    put((d1 <= 0) & (d2 <= 0), a)
    put((d3 >= 0) & (d4 <= d3), b)
    put((d6 >= 0) & (d5 <= d6), c)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = d1 / (d1 - d3); put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + v[:, None] * ab)
        w = d2 / (d2 - d6); put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + w[:, None] * ac)
        w2 = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + w2[:, None] * (c - b))
        den = 1.0 / (va + vb + vc); v = vb * den; w = vc * den
        put(np.ones(len(p), bool), a + ab * v[:, None] + ac * w[:, None])
    return np.linalg.norm(p - res, axis=1)


def mesh_dist(P, V, T):
    """unsigned distance of points P to mesh (V,T), chunked."""
    d = np.full(len(P), np.inf)
    A, B, C = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    nt = len(T)
    step = max(1, 200000 // nt)
    for i0 in range(0, len(P), step):
        p = P[i0:i0 + step]
        m = len(p)
        pp = np.repeat(p, nt, axis=0)
        dd = point_tri_dist(pp, np.tile(A, (m, 1)), np.tile(B, (m, 1)), np.tile(C, (m, 1)))
        d[i0:i0 + m] = dd.reshape(m, nt).min(1)
    return d


def winding(P, V, T):
    w = np.zeros(len(P))
    A, B, C = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    for i, p in enumerate(P):
        a = A - p; b = B - p; c = C - p
        la, lb, lc = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1), np.linalg.norm(c, axis=1)
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb
        w[i] = 2 * np.arctan2(det, den).sum() / (4 * np.pi)
    return w


def sdf_analytic(ob, c, R, P):
    if ob["kind"] == "sphere":
        return np.linalg.norm(P - c, axis=1) - ob["r"]
    if ob["kind"] == "plane":
        n = R @ np.array([0.0, 1.0, 0.0])
        return (P - c) @ n
    if ob["kind"] == "box":
        L = (P - c) @ R  # = R^T (p - c)
        h = np.asarray(ob["h"], float)
        q = np.abs(L) - h
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
    raise ValueError


def check_frame(P, tris, edges, free, obstacles, t, th, rest_len):
    """returns dict of violations for one frame (P float64 world positions)."""
    r = {}
    if not np.all(np.isfinite(P)):
        r["nan"] = int((~np.isfinite(P)).any(1).sum()); return r
    sc = seg_tri_pairs(P, edges, P, tris, True)
    if sc:
        r["self_cross"] = len(sc); r["self_cross_ex"] = sc[:3]
    L = np.linalg.norm(P[edges[:, 0]] - P[edges[:, 1]], axis=1)
    r["strain"] = float((L / rest_len - 1).max())
    eps = 4 * np.spacing(np.float32(np.abs(P).max())).astype(float)  # float32 written file
    Fp = P[free]
    Pp = P[~free]
    if len(Pp):
        pc = np.inf
        for ob in obstacles:
            c, R = pose(ob, t)
            if ob["kind"] == "mesh":
                V = (ob["V"] * ob.get("scale", 1.0)) @ R.T + c
                d = mesh_dist(Pp, V, ob["T"])
                if ob.get("closed", True):
                    d = np.where(np.abs(winding(Pp, V, ob["T"])) > 0.5, -d, d)
            else:
                d = sdf_analytic(ob, c, R, Pp)
            pc = min(pc, float(d.min()))
        r["pin_clear"] = pc
    for k, ob in enumerate(obstacles):
        c, R = pose(ob, t)
        if ob["kind"] == "mesh":
            V = (ob["V"] * ob.get("scale", 1.0)) @ R.T + c; T = ob["T"]
            lo = V.min(0) - th - 0.01; hi = V.max(0) + th + 0.01
            near = np.all((Fp >= lo) & (Fp <= hi), axis=1)
            if near.any():
                pn = Fp[near]
                d = mesh_dist(pn, V, T)
                if ob.get("closed", True):
                    w = winding(pn, V, T)
                    ins = np.abs(w) > 0.5
                    d = np.where(ins, -d, d)
                mn = float(d.min())
                r.setdefault("clear", {})[k] = mn
                if mn < th - 1e-4 - eps:
                    r.setdefault("obs_viol", {})[k] = dict(min_d=mn, n=int((d < th - 1e-4 - eps).sum()), inside=int((d < 0).sum()))
            OE = edges_from(T)
            h1 = seg_tri_pairs(P, edges, V, T, False)
            h2 = seg_tri_pairs(V, OE, P, tris, False)
            if h1 or h2:
                r.setdefault("obs_cross", {})[k] = (len(h1), len(h2))
        else:
            d = sdf_analytic(ob, c, R, Fp)
            mn = float(d.min()) if len(d) else np.inf
            r.setdefault("clear", {})[k] = mn
            if mn < th - 1e-4 - eps:
                r.setdefault("obs_viol", {})[k] = dict(min_d=mn, n=int((d < th - 1e-4 - eps).sum()), inside=int((d < 0).sum()))
            # edges' points inside analytic obstacle
            ts = np.linspace(0, 1, 7)[:, None, None]
            fe = edges[free[edges[:, 0]] & free[edges[:, 1]]]
            S = (P[fe[:, 0]][None] * (1 - ts) + P[fe[:, 1]][None] * ts).reshape(-1, 3)
            ds = sdf_analytic(ob, c, R, S)
            if ds.min() < -eps - 1e-6:
                r.setdefault("edge_inside", {})[k] = float(ds.min())
    return r


def surface_samples(ob, c, R, n=12):
    """Points on an obstacle's surface (world), for `obstacles_pinch`: a mesh's vertices, a box's
    face grids, a sphere's Fibonacci points; none for a plane (unbounded)."""
    if ob["kind"] == "mesh":
        return (ob["V"] * ob.get("scale", 1.0)) @ R.T + c
    if ob["kind"] == "sphere":
        k = np.arange(n * n) + 0.5
        phi = np.arccos(1 - 2 * k / (n * n)); th = np.pi * (1 + 5 ** 0.5) * k
        return c + ob["r"] * np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], 1)
    if ob["kind"] == "box":
        h = np.asarray(ob["h"], float); g = np.linspace(-1, 1, n); out = []
        for a in range(3):
            b, e = [i for i in range(3) if i != a]
            for s in (-1, 1):
                U, W = np.meshgrid(g, g)
                L = np.zeros((U.size, 3)); L[:, a] = s; L[:, b] = U.ravel(); L[:, e] = W.ravel()
                out.append(L * h)
        return np.concatenate(out) @ R.T + c
    return np.zeros((0, 3))


def obstacles_pinch(obstacles, t, gap):
    """Whether two obstacles come within ``gap`` of each other (or into each other) at time t:
    cloth between them cannot keep its thickness from both (a forced failure)."""
    poses = [pose(ob, t) for ob in obstacles]
    for i, a in enumerate(obstacles):
        S = surface_samples(a, *poses[i])
        if not len(S):
            continue
        for j, b in enumerate(obstacles):
            if j == i:
                continue
            c, R = poses[j]
            if b["kind"] == "mesh":
                V = (b["V"] * b.get("scale", 1.0)) @ R.T + c
                lo, hi = V.min(0) - gap, V.max(0) + gap
                near = np.all((S >= lo) & (S <= hi), axis=1)
                if not near.any():
                    continue
                d = mesh_dist(S[near], V, b["T"])
                d = np.where(np.abs(winding(S[near], V, b["T"])) > 0.5, -d, d)
            else:
                d = sdf_analytic(b, c, R, S)
            if d.min() < gap:
                return True
    return False
