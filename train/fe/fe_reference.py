"""Finite-element reference for contact on an elastic layer bonded to a rigid plate.

What it computes
----------------
An independent check of the contact-mechanics solver (which uses a Fourier closed form): the same
problems solved by the finite-element method with scikit-fem, written to
`data/fixtures/elastic-fe/bonded-layer.json`. Five cases on a layer h = 3.2 mm, E = 150 kPa,
nu = 0.42 (`sphere`, `sphere-deep`, `flat-punch`, `flat-punch-sheared`, `two-bumps`, see `CASES`),
each solved on a base mesh and on a mesh refined by `--refine` (the fixture holds the refined
solution, `converged_change_pct` the change from the base one). `--validate` instead runs the checks
of the FE itself: Hertz and the flat punch on a thick layer, and uniform pressure on the thin layer.

Conventions (those of the gel frame)
------------------------------------
* Linear elasticity, small strain. The layer occupies -h < z < 0; z = -h is bonded to a rigid plate
  (u = 0); z = 0 is the contact surface; x, y lie in the surface; z points out of the gel.
* w = -u_z: positive when the surface is pushed into the gel. Pressure p > 0 is compressive: the
  traction on the gel is (tau_x, tau_y, -p); tau is the force per area the object exerts on the gel.
* Units mm and kPa, so a force sum(p * area) is in mN; the fixture gives newtons (/1000).
* Markers: 19 x 19 at pitch 1 mm centred on the origin, marker (row, col) at x = (col - 9) mm,
  y = (row - 9) mm, row-major.

How
---
* Trilinear hexahedra (ElementHex1) on a tensor-product mesh, graded: `--h-fine` (0.15 mm) near the
  contact, <= 0.5 mm over the lattice, up to 2.5 mm beyond; 0.1 mm thick elements at the surface,
  growing to 0.5 mm at the plate. The square domain (half-width 23 mm >= 9.5 + 4 h) is centred on
  the indenter, so an axisymmetric indenter is solved on a quarter model (mirror planes through its
  centre) even when it is off the origin; the markers then sample the unfolded field.
* Frictionless contact: active set on the surface nodes. Active nodes get u_z = -(d - r^2 / 2R)
  (tangential free); a node with tensile reaction is released, a free node that penetrates the
  indenter is added, until the set no longer changes.
* The bonded sheared punch is linear (all three components prescribed on the face): it is the sum of
  the bonded normal indentation (quarter model) and the unit x-shear (quarter model, antisymmetric
  about x = 0), the y-shear being the x-shear rotated by 90 degrees (circular punch, square domain).
* Linear systems: CG preconditioned by smoothed-aggregation AMG (pyamg), relative residual 1e-10.
* Tractions: nodal reactions K u at the surface nodes divided by the nodes' tributary areas (for
  bilinear faces on a rectangular grid a uniform traction's consistent nodal load is exactly the
  traction times that area). Markers get (a) `markers`: the traction averaged over the marker's
  1 x 1 mm cell (reactions apportioned by tributary-area overlap), so that sum(p) * pitch^2 is the
  force, and (b) `markers_point`: the nodal traction interpolated bilinearly at the marker.
  Displacements at the markers are the FE field interpolated (bilinear on the surface face).
* Contact area: sum of the active nodes' tributary areas (`contact_area_nodes_mm2`); for the
  spheres the reported area is pi a^2 with the radius a where the pressure vanishes, fitted from
  p^2 linear in r over the outer active ring (p ~ sqrt(a - r) at a smooth contact's edge); for
  `two-bumps` that is done per bump and summed. For the punches the area is the face, pi a^2.

Run time (2-core machine, shared): all five cases, base + refined meshes, 11 minutes
(`python train/fe/fe_reference.py --out data/fixtures/elastic-fe`), `two-bumps` (full model, 627k
unknowns refined) 5.5 of them; `--validate` 1.5-2 minutes. Needs `train/fe/requirements-fe.txt`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyamg
import scipy.sparse as sp
import skfem
from scipy.interpolate import RegularGridInterpolator
from skfem import Basis, ElementHex1, ElementVector, MeshHex, asm, condense
from skfem.models.elasticity import lame_parameters, linear_elasticity

LAYER = dict(thickness_mm=3.2, modulus_kpa=150.0, poisson=0.42)
ROWS = COLS = 19
PITCH = 1.0
HALF_WIDTH = 23.0  # domain half-width, >= lattice edge (9.5) + 4 h (12.8)
LATTICE_EDGE = 9.5 + 0.5  # cells stay <= h_lattice out to here

CASES = {
    "sphere": dict(kind="spheres", spheres=[dict(center_mm=[0.3, -0.2], radius_mm=6.0, depth_mm=0.35)]),
    "sphere-deep": dict(kind="spheres", spheres=[dict(center_mm=[0.0, 0.0], radius_mm=6.0, depth_mm=0.6)]),
    "flat-punch": dict(kind="flat_punch", center_mm=[0.0, 0.0], radius_mm=2.5, depth_mm=0.12, bonded=False),
    "flat-punch-sheared": dict(
        kind="flat_punch", center_mm=[0.0, 0.0], radius_mm=2.5, depth_mm=0.12, bonded=True, shift_mm=[0.05, 0.02]
    ),
    "two-bumps": dict(
        kind="spheres",
        spheres=[
            dict(center_mm=[-2.5, 0.0], radius_mm=3.0, depth_mm=0.25),
            dict(center_mm=[2.5, 0.5], radius_mm=3.0, depth_mm=0.25),
        ],
    ),
}


@dataclass
class Mesh:
    """Sizes of a graded tensor mesh; `scale` < 1 refines every size."""

    h_fine: float = 0.15
    h_lattice: float = 0.5
    h_max: float = 2.5
    growth: float = 0.25  # size grows by this much per mm of distance from the fine zone
    hz_top: float = 0.1
    hz_max: float = 0.5
    scale: float = 1.0
    half_width: float = HALF_WIDTH  # of the square domain, mm (not scaled)


# ---------------------------------------------------------------------------------------------
# Mesh


def graded_axis(lo, hi, fine, h_fine, h_lattice, h_max, growth, lattice=(-LATTICE_EDGE, LATTICE_EDGE)):
    """Node coordinates from lo to hi: h_fine inside the `fine` intervals, growing linearly with the
    distance from them, capped at h_lattice inside `lattice` and h_max outside."""

    def size(x):
        dist = min(max(a - x, 0.0, x - b) for a, b in fine)
        cap = h_lattice if lattice[0] <= x <= lattice[1] else h_max
        return min(h_fine + growth * dist, cap)

    xs = [lo]
    while xs[-1] < hi - 1e-9:
        step = size(xs[-1])
        for _ in range(3):  # do not step over the start of a finer zone
            step = min(step, size(xs[-1] + step))
        xs.append(xs[-1] + step)
    xs[-1] = hi
    if len(xs) > 2 and xs[-1] - xs[-2] < 0.3 * (xs[-2] - xs[-3]):
        del xs[-2]  # no sliver at the end
    return np.array(xs)


def depth_axis(h, mesh: Mesh):
    """z nodes from -h to 0, thinnest at the surface."""
    d = graded_axis(0.0, h, [(0.0, 0.0)], mesh.hz_top * mesh.scale, mesh.hz_max * mesh.scale,
                    mesh.hz_max * mesh.scale, 0.25, lattice=(0.0, h))
    return -d[::-1]


@dataclass
class Model:
    xs: np.ndarray
    ys: np.ndarray
    zs: np.ndarray
    basis: Basis
    K: sp.csr_matrix
    surf: np.ndarray  # surf[i, j]: node index of the surface node (xs[i], ys[j], 0)
    bottom_dofs: np.ndarray


def build_model(xs, ys, zs, modulus, poisson) -> Model:
    mesh = MeshHex.init_tensor(xs, ys, zs)
    basis = Basis(mesh, ElementVector(ElementHex1()), intorder=2)
    K = asm(linear_elasticity(*lame_parameters(modulus, poisson)), basis).tocsr()
    p = mesh.p
    top = np.flatnonzero(np.isclose(p[2], 0.0))
    surf = np.full((len(xs), len(ys)), -1)
    surf[np.searchsorted(xs, p[0, top] - 1e-9), np.searchsorted(ys, p[1, top] - 1e-9)] = top
    assert (surf >= 0).all()
    bottom = np.flatnonzero(np.isclose(p[2], zs[0]))
    return Model(xs, ys, zs, basis, K, surf, basis.nodal_dofs[:, bottom].ravel())


def tributary(xs):
    """Length of each node's share of the axis (half cells at both ends)."""
    mid = 0.5 * (xs[1:] + xs[:-1])
    edges = np.concatenate([[xs[0]], mid, [xs[-1]]])
    return edges[1:] - edges[:-1], edges


# ---------------------------------------------------------------------------------------------
# Solve


def solve(model: Model, prescribed: dict[int, float], x0=None):
    """Displacement with u = 0 on the plate and u[dof] = value on `prescribed`; no other loads."""
    dofs = np.array(list(prescribed), dtype=int)
    D = np.concatenate([model.bottom_dofs, dofs])
    x = np.zeros(model.K.shape[0])
    x[dofs] = np.array(list(prescribed.values()))
    A, b, _, I = condense(model.K, np.zeros_like(x), x=x, D=D)
    ml = pyamg.smoothed_aggregation_solver(A.tocsr(), symmetry="symmetric", strength="symmetric")
    guess = None if x0 is None else x0[I]
    x[I] = ml.solve(b, x0=guess, tol=1e-10, accel="cg", maxiter=2000)
    # pyamg stops silently at maxiter: check that the residual really reached the tolerance
    if np.linalg.norm(b - A @ x[I]) > 1e-8 * np.linalg.norm(b):
        raise RuntimeError("CG did not converge")
    return x


def surface_fields(model: Model, u):
    """Surface displacement (3, nx, ny) and traction on the gel (3, nx, ny) from the reactions."""
    nd = model.basis.nodal_dofs[:, model.surf]  # (3, nx, ny)
    reaction = model.K @ u
    tx, _ = tributary(model.xs)
    ty, _ = tributary(model.ys)
    area = tx[:, None] * ty[None, :]
    return u[nd], reaction[nd] / area


# symmetry: for each mirror plane, "sym" (mirror-symmetric field) or "anti" (antisymmetric). The
# component normal to the plane is odd under "sym", the two in-plane ones under "anti".
def odd_components(plane_axis, kind):
    return {plane_axis} if kind == "sym" else {0, 1, 2} - {plane_axis}


def symmetry_dofs(model: Model, sym):
    """Dirichlet u = 0 for the odd components on the mirror planes x = 0 and y = 0."""
    dofs = []
    p = model.basis.mesh.p
    for axis, kind in enumerate(sym):
        if kind is None:
            continue
        nodes = np.flatnonzero(np.isclose(p[axis], 0.0))
        for c in odd_components(axis, kind):
            dofs.append(model.basis.nodal_dofs[c, nodes])
    return np.concatenate(dofs) if dofs else np.array([], dtype=int)


def unfold(xs, ys, fields, sym):
    """Mirror quarter-model surface fields (3, nx, ny) over x = 0 and y = 0 into the full square."""
    out = fields.copy()
    for axis, kind in enumerate(sym):
        if kind is None:
            continue
        odd = odd_components(axis, kind)
        sign = np.array([-1.0 if c in odd else 1.0 for c in range(3)])[:, None, None]
        first = [slice(None)] * 3
        first[axis + 1] = slice(0, 1)
        for c in odd:  # an odd component vanishes on its mirror plane (kills the symmetry reactions)
            out[(c, *first[1:])] = 0.0
        mirrored = np.flip(out, axis=axis + 1)
        body = [slice(None)] * 3
        body[axis + 1] = slice(0, -1)
        out = np.concatenate([sign * mirrored[tuple(body)], out], axis=axis + 1)
    xs = np.concatenate([-xs[:0:-1], xs]) if sym[0] else xs
    ys = np.concatenate([-ys[:0:-1], ys]) if sym[1] else ys
    return xs, ys, out


# ---------------------------------------------------------------------------------------------
# Contact


def indenter_depth(model: Model, spheres, center):
    """Per surface node, how far the spheres' lowest surface lies below z = 0 (d - r^2 / 2R, max
    over the spheres); `center` is the model origin in lattice coordinates."""
    X, Y = np.meshgrid(model.xs + center[0], model.ys + center[1], indexing="ij")
    target = np.full(X.shape, -np.inf)
    for s in spheres:
        r2 = (X - s["center_mm"][0]) ** 2 + (Y - s["center_mm"][1]) ** 2
        target = np.maximum(target, s["depth_mm"] - r2 / (2 * s["radius_mm"]))
    return target


def active_set(model: Model, target, active, sym, log, max_iter=40):
    """Frictionless contact: u_z = -target on active nodes. Returns u, fields, active, iterations."""
    zdofs = model.basis.nodal_dofs[2, model.surf]
    fixed = symmetry_dofs(model, sym)
    u = None
    for it in range(1, max_iter + 1):
        prescribed = {int(d): 0.0 for d in fixed}
        prescribed.update({int(d): -float(t) for d, t in zip(zdofs[active], target[active])})
        u = solve(model, prescribed, x0=u)
        disp, trac = surface_fields(model, u)
        pressure, w = -trac[2], -disp[2]
        tol = 1e-7 * np.nanmax(target[np.isfinite(target)])
        release = active & (pressure < 0)
        add = ~active & (w < target - tol)
        log(f"    active set iteration {it}: {active.sum()} active, release {release.sum()}, add {add.sum()}")
        if not release.any() and not add.any():
            return u, disp, trac, active, it
        active = (active & ~release) | add
    raise RuntimeError("active set did not converge")


# ---------------------------------------------------------------------------------------------
# Cases


def make_axes(mesh: Mesh, fine_x, fine_y, quarter, half_width=None, thickness=LAYER["thickness_mm"]):
    s = mesh.scale
    half_width = half_width or mesh.half_width
    lo = 0.0 if quarter else -half_width
    xs = graded_axis(lo, half_width, fine_x, mesh.h_fine * s, mesh.h_lattice * s, mesh.h_max * s, mesh.growth)
    ys = graded_axis(lo, half_width, fine_y, mesh.h_fine * s, mesh.h_lattice * s, mesh.h_max * s, mesh.growth)
    return xs, ys, depth_axis(thickness, mesh)


def solve_spheres(spec, mesh: Mesh, log, layer=LAYER, half_width=None):
    spheres = spec["spheres"]
    quarter = len(spheres) == 1
    if quarter:  # domain centred on the sphere: mirror-symmetric about both planes through it
        center = np.array(spheres[0]["center_mm"], float)
        a0 = 1.2 * math.sqrt(spheres[0]["radius_mm"] * spheres[0]["depth_mm"])
        fine_x = fine_y = [(0.0, a0 + 0.3)]
    else:
        center = np.zeros(2)
        fine_x, fine_y = [], []
        for s in spheres:
            a0 = 1.2 * math.sqrt(s["radius_mm"] * s["depth_mm"]) + 0.3
            fine_x.append((s["center_mm"][0] - a0, s["center_mm"][0] + a0))
            fine_y.append((s["center_mm"][1] - a0, s["center_mm"][1] + a0))
    xs, ys, zs = make_axes(mesh, fine_x, fine_y, quarter, half_width, layer["thickness_mm"])
    model = build_model(xs, ys, zs, layer["modulus_kpa"], layer["poisson"])
    log(f"  mesh {len(xs)} x {len(ys)} x {len(zs)} nodes, {model.K.shape[0]} dofs")
    sym = ("sym", "sym") if quarter else (None, None)
    target = indenter_depth(model, spheres, center)
    u, disp, trac, active, iters = active_set(model, target, target > 0.5 * target.max(), sym, log)
    return dict(model=model, sym=sym, center=center, disp=disp, trac=trac, active=active, iterations=iters)


def punch_face(model: Model, spec):
    X, Y = np.meshgrid(model.xs, model.ys, indexing="ij")
    return X**2 + Y**2 <= spec["radius_mm"] ** 2 + 1e-12


def solve_flat_punch(spec, mesh: Mesh, log, layer=LAYER, half_width=None):
    a = spec["radius_mm"]
    xs, ys, zs = make_axes(mesh, [(0.0, a + 0.3)], [(0.0, a + 0.3)], True, half_width, layer["thickness_mm"])
    model = build_model(xs, ys, zs, layer["modulus_kpa"], layer["poisson"])
    log(f"  mesh {len(xs)} x {len(ys)} x {len(zs)} nodes, {model.K.shape[0]} dofs")
    face = punch_face(model, spec)
    d = spec["depth_mm"]
    center = np.array(spec["center_mm"], float)
    sym = ("sym", "sym")
    if not spec.get("bonded"):
        target = np.where(face, d, -np.inf)
        u, disp, trac, active, iters = active_set(model, target, face.copy(), sym, log)
        if active.sum() != face.sum():
            log("  warning: the frictionless punch lost contact over part of its face")
        return dict(model=model, sym=sym, center=center, disp=disp, trac=trac, active=active, iterations=iters)
    # bonded: normal indentation + unit x-shear, both on quarter models, combined below
    nd = model.basis.nodal_dofs[:, model.surf[face]]
    normal = {int(q): 0.0 for q in symmetry_dofs(model, sym)}
    for c, value in enumerate((0.0, 0.0, -d)):
        normal.update({int(q): value for q in nd[c]})
    u_n = solve(model, normal)
    shear_sym = ("anti", "sym")
    shear = {int(q): 0.0 for q in symmetry_dofs(model, shear_sym)}
    for c, value in enumerate((1.0, 0.0, 0.0)):
        shear.update({int(q): value for q in nd[c]})
    u_s = solve(model, shear)
    parts = [(surface_fields(model, u_n), sym), (surface_fields(model, u_s), shear_sym)]
    return dict(model=model, center=center, active=face, iterations=1, parts=parts, shift=spec["shift_mm"])


def full_surface(result):
    """Unfolded surface displacement and traction (3, nx, ny) on the full square, local coords."""
    model = result["model"]
    if "parts" not in result:
        xs, ys, disp = unfold(model.xs, model.ys, result["disp"], result["sym"])
        _, _, trac = unfold(model.xs, model.ys, result["trac"], result["sym"])
        _, _, act = unfold(model.xs, model.ys, np.repeat(result["active"][None] * 1.0, 3, 0), result["sym"])
        return xs, ys, disp, trac, act[2] > 0.5
    (dn, tn), sym_n = result["parts"][0]
    (ds, ts), sym_s = result["parts"][1]
    xs, ys, disp = unfold(model.xs, model.ys, dn, sym_n)
    _, _, trac = unfold(model.xs, model.ys, tn, sym_n)
    _, _, dsx = unfold(model.xs, model.ys, ds, sym_s)
    _, _, tsx = unfold(model.xs, model.ys, ts, sym_s)
    assert np.allclose(xs, ys)
    sx, sy = result["shift"]

    def rotate(f):  # y-shear(p) = R x-shear(R^T p), R the +90 degree rotation: R^T (x, y) = (y, -x)
        g = np.swapaxes(np.flip(f, axis=2), 1, 2)  # g[:, i, j] = f[:, j, -1 - i]
        return np.stack([-g[1], g[0], g[2]])

    disp = disp + sx * dsx + sy * rotate(dsx)
    trac = trac + sx * tsx + sy * rotate(tsx)
    _, _, act = unfold(model.xs, model.ys, np.repeat(result["active"][None] * 1.0, 3, 0), sym_n)
    return xs, ys, disp, trac, act[2] > 0.5


# ---------------------------------------------------------------------------------------------
# Outputs


def marker_xy():
    col, row = np.meshgrid(np.arange(COLS), np.arange(ROWS))  # row-major: row outer
    return ((col - (COLS - 1) / 2) * PITCH).ravel(), ((row - (ROWS - 1) / 2) * PITCH).ravel()


def overlap_matrix(edges, centers, half):
    """overlap[m, i]: length shared by node i's tributary interval and marker cell m."""
    lo = np.maximum(edges[None, :-1], centers[:, None] - half)
    hi = np.minimum(edges[None, 1:], centers[:, None] + half)
    return np.clip(hi - lo, 0.0, None)


def radius_from_pressure(r, pressure, active, h_cell):
    """Where p vanishes: p^2 linear in r fitted over the active nodes of the outer ring."""
    ra = r[active]
    ring = active & (r > ra.max() - 2.5 * h_cell) & (pressure > 0)
    if ring.sum() < 3:
        return float(ra.max())
    slope, icept = np.polyfit(r[ring], pressure[ring] ** 2, 1)
    return float(-icept / slope) if slope < 0 else float(ra.max())


def summarize(name, spec, result, h_fine):
    xs, ys, disp, trac, active = full_surface(result)
    center = result["center"]
    tx, ex = tributary(xs)
    ty, ey = tributary(ys)
    area = tx[:, None] * ty[None, :]
    pressure, tau = -trac[2], trac[:2]
    X, Y = np.meshgrid(xs + center[0], ys + center[1], indexing="ij")
    force = (pressure * area).sum()
    truth = dict(
        contact_area_nodes_mm2=float(area[active].sum()),
        force_N=float(force / 1000),
        shear_x_N=float((tau[0] * area).sum() / 1000),
        shear_y_N=float((tau[1] * area).sum() / 1000),
        centroid_x_mm=float((pressure * area * X).sum() / force),
        centroid_y_mm=float((pressure * area * Y).sum() / force),
    )
    if spec["kind"] == "flat_punch":
        a = spec["radius_mm"]
        truth.update(contact_area_mm2=math.pi * a * a, contact_radius_mm=a)
    else:
        radii = []
        for s in spec["spheres"]:  # each bump: its own nodes (nearer its centre than the other's)
            R = np.hypot(X - s["center_mm"][0], Y - s["center_mm"][1])
            mine = np.ones_like(active)
            for o in spec["spheres"]:
                mine &= R <= np.hypot(X - o["center_mm"][0], Y - o["center_mm"][1]) + 1e-12
            radii.append(radius_from_pressure(R.ravel(), pressure.ravel(), (active & mine).ravel(), h_fine))
        truth["contact_area_mm2"] = float(sum(math.pi * a * a for a in radii))
        truth["contact_radius_mm"] = radii[0] if len(radii) == 1 else None
        truth["contact_radii_mm"] = radii
    # markers, in local coordinates of the (possibly shifted) model
    mx, my = marker_xy()
    lx, ly = mx - center[0], my - center[1]
    point = {}
    for key, field in (("ux_mm", disp[0]), ("uy_mm", disp[1]), ("w_mm", -disp[2]),
                       ("pressure_kpa", pressure), ("tau_x_kpa", tau[0]), ("tau_y_kpa", tau[1])):
        point[key] = RegularGridInterpolator((xs, ys), field)(np.stack([lx, ly], axis=1))
    # cell averages: marker cells of the lattice, in local coordinates
    ox = overlap_matrix(ex, (np.arange(COLS) - (COLS - 1) / 2) * PITCH - center[0], PITCH / 2)
    oy = overlap_matrix(ey, (np.arange(ROWS) - (ROWS - 1) / 2) * PITCH - center[1], PITCH / 2)
    cell = {}
    for key, field in (("pressure_kpa", pressure), ("tau_x_kpa", tau[0]), ("tau_y_kpa", tau[1])):
        # field * area / tributary gives per-node traction spread uniformly over its rectangle
        per_col_row = ox @ field @ oy.T / PITCH**2  # [col, row]
        cell[key] = per_col_row.T.ravel()  # row-major
    markers = {k: point[k] for k in ("ux_mm", "uy_mm", "w_mm")}
    markers.update(cell)
    markers_point = {k: point[k] for k in ("pressure_kpa", "tau_x_kpa", "tau_y_kpa")}
    return truth, markers, markers_point


def sig(values, digits=6):
    return [float(f"{v:.{digits}g}") for v in np.asarray(values, float)]


def run_case(name, mesh: Mesh, log):
    spec = CASES[name]
    t0 = time.time()
    if spec["kind"] == "spheres":
        result = solve_spheres(spec, mesh, log)
    else:
        result = solve_flat_punch(spec, mesh, log)
    truth, markers, markers_point = summarize(name, spec, result, mesh.h_fine * mesh.scale)
    nodes = result["model"].basis.mesh.p.shape[1]
    elements = result["model"].basis.mesh.t.shape[1]
    log(f"  {name}: F = {truth['force_N']:.5f} N, area {truth['contact_area_mm2']:.4f} mm2, "
        f"{time.time() - t0:.0f} s")
    return dict(truth=truth, markers=markers, markers_point=markers_point, nodes=nodes, elements=elements,
                iterations=result["iterations"], seconds=time.time() - t0,
                quarter="parts" in result or result["sym"][0] is not None)


def change_pct(coarse, fine):
    """Largest change of the truth figures and of w at the markers, % of the fine value's scale."""
    out = {}
    for key in ("force_N", "contact_area_mm2"):
        out[key] = 100 * abs(fine["truth"][key] - coarse["truth"][key]) / abs(fine["truth"][key])
    for key in ("shear_x_N",):
        if abs(fine["truth"][key]) > 1e-9:
            out[key] = 100 * abs(fine["truth"][key] - coarse["truth"][key]) / abs(fine["truth"][key])
    w_f, w_c = np.asarray(fine["markers"]["w_mm"]), np.asarray(coarse["markers"]["w_mm"])
    out["w_markers_max"] = 100 * np.abs(w_f - w_c).max() / np.abs(w_f).max()
    return out


def write_fixture(out_dir: Path, results, argv, mesh_desc):
    cases = []
    for name, (base, fine) in results.items():
        spec = CASES[name]
        indenter = {"shape": "sphere" if spec["kind"] == "spheres" else "flat_punch"}
        indenter.update({k: v for k, v in spec.items() if k != "kind"})
        if spec["kind"] == "spheres":
            indenter["friction"] = "frictionless"
        else:
            indenter["friction"] = "bonded (full stick)" if spec["bonded"] else "frictionless"
        change = change_pct(base, fine)
        cases.append(dict(
            name=name,
            indenter=indenter,
            markers={k: sig(v) for k, v in fine["markers"].items()},
            markers_point={k: sig(v) for k, v in fine["markers_point"].items()},
            truth={k: (None if v is None else (sig(v) if isinstance(v, list) else float(f"{v:.6g}")))
                   for k, v in fine["truth"].items()},
            mesh=dict(nodes=fine["nodes"], elements=fine["elements"],
                      converged_change_pct=float(f"{max(change.values()):.3g}"),
                      change_pct_by_figure={k: float(f"{v:.3g}") for k, v in change.items()},
                      coarse_nodes=base["nodes"], symmetry="quarter model" if fine["quarter"] else "full model",
                      active_set_iterations=fine["iterations"]),
        ))
    doc = dict(
        generator=dict(script="train/fe/fe_reference.py", command="python train/fe/fe_reference.py " + " ".join(argv)),
        library=dict(name="scikit-fem", version=skfem.__version__, element="ElementHex1 (trilinear hexahedra)",
                     solver=f"pyamg {pyamg.__version__} smoothed aggregation + CG, rtol 1e-10"),
        layer=LAYER,
        lattice=dict(rows=ROWS, cols=COLS, pitch_mm=PITCH),
        conventions=dict(
            frame="gel frame: x, y in the surface, z out of the gel; layer -h < z < 0 bonded to a rigid plate at z = -h",
            w="w = -u_z, positive into the gel",
            pressure="p > 0 compressive; traction on the gel = (tau_x, tau_y, -p); kPa",
            markers="traction: mean over the marker's pitch x pitch cell (sum * pitch^2 = force); "
                    "displacement: FE field at the marker",
            markers_point="nodal traction (reaction / tributary area) interpolated at the marker",
            contact_area="spheres: pi a^2, a where p vanishes (p^2 fit); punches: the face; "
                         "contact_area_nodes_mm2: active nodes' tributary areas",
        ),
        mesh_sizes=mesh_desc,
        cases=cases,
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "bonded-layer.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


# ---------------------------------------------------------------------------------------------
# Validation of the FE itself


def validate(mesh: Mesh, log):
    E, nu = LAYER["modulus_kpa"], LAYER["poisson"]
    estar = E / (1 - nu**2)
    thick = dict(thickness_mm=40.0, modulus_kpa=E, poisson=nu)
    thick_mesh = Mesh(h_fine=mesh.h_fine * 0.6, h_lattice=4.0, h_max=6.0, growth=0.3,
                      hz_top=mesh.hz_top * 0.9, hz_max=6.0, scale=mesh.scale)
    out = {}
    # Hertz on a thick layer
    R, d = 6.0, 0.15
    spec = dict(kind="spheres", spheres=[dict(center_mm=[0.0, 0.0], radius_mm=R, depth_mm=d)])
    res = solve_spheres(spec, thick_mesh, log, layer=thick, half_width=40.0)
    truth, _, _ = summarize("hertz", spec, res, thick_mesh.h_fine * thick_mesh.scale)
    F_h, a_h = 4 / 3 * estar * math.sqrt(R) * d**1.5 / 1000, math.sqrt(R * d)
    out["hertz"] = dict(force_N=truth["force_N"], hertz_force_N=F_h, radius_mm=truth["contact_radius_mm"],
                        hertz_radius_mm=a_h, radius_nodes_mm=math.sqrt(truth["contact_area_nodes_mm2"] / math.pi),
                        dofs=res["model"].K.shape[0])
    log(f"  Hertz: {out['hertz']}")
    # flat punch on a thick layer
    a, d = 1.0, 0.05
    spec = dict(kind="flat_punch", center_mm=[0.0, 0.0], radius_mm=a, depth_mm=d, bonded=False)
    res = solve_flat_punch(spec, thick_mesh, log, layer=thick, half_width=40.0)
    truth, _, _ = summarize("punch", spec, res, thick_mesh.h_fine)
    face_area = truth["contact_area_nodes_mm2"]
    out["flat_punch"] = dict(force_N=truth["force_N"], analytic_N=2 * a * estar * d / 1000,
                             face_nodes_area_mm2=face_area, face_area_mm2=math.pi * a * a,
                             dofs=res["model"].K.shape[0])
    log(f"  flat punch: {out['flat_punch']}")
    # thin layer: uniform pressure over the whole top gives confined compression far from the edges
    p = 10.0
    xs, ys, zs = make_axes(mesh, [(0.0, 0.5)], [(0.0, 0.5)], True, half_width=60.0)  # edges ~20 h away
    model = build_model(xs, ys, zs, E, nu)
    tx, _ = tributary(xs)
    ty, _ = tributary(ys)
    f = np.zeros(model.K.shape[0])
    f[model.basis.nodal_dofs[2, model.surf]] = -p * tx[:, None] * ty[None, :]
    D = np.concatenate([model.bottom_dofs, symmetry_dofs(model, ("sym", "sym"))])
    A, b, _, I = condense(model.K, f, D=D)
    u = np.zeros_like(f)
    ml = pyamg.smoothed_aggregation_solver(A.tocsr(), symmetry="symmetric", strength="symmetric")
    u[I] = ml.solve(b, tol=1e-10, accel="cg", maxiter=2000)
    assert np.linalg.norm(b - A @ u[I]) < 1e-8 * np.linalg.norm(b)
    w0 = -u[model.basis.nodal_dofs[2, model.surf[0, 0]]]
    h = LAYER["thickness_mm"]
    out["uniform_pressure"] = dict(w_center_mm=float(w0),
                                   analytic_mm=p * h * (1 + nu) * (1 - 2 * nu) / (E * (1 - nu)))
    log(f"  uniform pressure: {out['uniform_pressure']}")
    return out


# ---------------------------------------------------------------------------------------------


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("data/fixtures/elastic-fe"), help="folder for bonded-layer.json")
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--h-fine", type=float, default=0.15, help="element size near the contact, mm (base mesh)")
    ap.add_argument("--refine", type=float, default=1.5, help="the fixture's mesh: every size divided by this")
    ap.add_argument("--no-refine", action="store_true", help="base mesh only (no convergence figure)")
    ap.add_argument("--half-width", type=float, default=HALF_WIDTH, help="of the square domain, mm")
    ap.add_argument("--validate", action="store_true", help="run the validation against analytic solutions")
    ap.add_argument("--validate-out", type=Path, help="also write the validation figures to this JSON file")
    args = ap.parse_args(argv)
    log = lambda s: print(s, flush=True)  # noqa: E731
    base = Mesh(h_fine=args.h_fine, half_width=args.half_width)
    if args.validate:
        t0 = time.time()
        figures = validate(base, log)
        log(f"validation done in {time.time() - t0:.0f} s")
        if args.validate_out:
            args.validate_out.write_text(json.dumps(figures, indent=1) + "\n")
        return figures
    fine = Mesh(h_fine=args.h_fine, scale=1 / args.refine, half_width=args.half_width)
    results = {}
    t0 = time.time()
    for name in args.cases:
        log(f"{name}: base mesh")
        coarse = run_case(name, base, log)
        if args.no_refine:
            results[name] = (coarse, coarse)
            continue
        log(f"{name}: refined mesh (sizes / {args.refine})")
        results[name] = (coarse, run_case(name, fine, log))
        log(f"  change: {change_pct(coarse, results[name][1])}")
    mesh_desc = dict(base=vars(base), refined=None if args.no_refine else vars(fine),
                     half_width_mm=args.half_width)
    path = write_fixture(args.out, results, argv, mesh_desc)
    log(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB) in {time.time() - t0:.0f} s")
    return results


if __name__ == "__main__":
    main()
