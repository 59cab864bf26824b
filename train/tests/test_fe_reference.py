"""The finite-element contact reference (`train/fe/fe_reference.py`): a coarse flat punch on a thick
layer against the analytic F = 2 a E* d, and the committed fixture's schema and internal consistency
(force = sum of the markers' cell pressures times the cell area; w follows the indenter inside the
contact)."""

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "data" / "fixtures" / "elastic-fe" / "bonded-layer.json"
N = 19 * 19


def _load_script():
    path = ROOT / "train" / "fe" / "fe_reference.py"
    spec = importlib.util.spec_from_file_location("fe_reference", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["fe_reference"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_coarse_flat_punch_on_a_thick_layer_matches_the_half_space():
    pytest.importorskip("skfem")
    pytest.importorskip("pyamg")
    fe = _load_script()
    E, nu, a, d = 150.0, 0.42, 1.0, 0.05
    layer = dict(thickness_mm=20.0, modulus_kpa=E, poisson=nu)
    mesh = fe.Mesh(h_fine=0.2, h_lattice=3.0, h_max=5.0, growth=0.35, hz_top=0.2, hz_max=5.0)
    spec = dict(kind="flat_punch", center_mm=[0.0, 0.0], radius_mm=a, depth_mm=d, bonded=False)
    result = fe.solve_flat_punch(spec, mesh, lambda s: None, layer=layer, half_width=20.0)
    truth, markers, _ = fe.summarize("punch", spec, result, mesh.h_fine)
    analytic = 2 * a * E / (1 - nu**2) * d / 1000
    assert truth["force_N"] == pytest.approx(analytic, rel=0.08)
    assert abs(truth["centroid_x_mm"]) < 1e-6 and abs(truth["shear_x_N"]) < 1e-9
    assert np.asarray(markers["w_mm"])[N // 2] == pytest.approx(d, rel=1e-6)


@pytest.fixture(scope="module")
def fixture():
    return json.loads(FIXTURE.read_text())


def test_fixture_schema(fixture):
    assert fixture["layer"] == dict(thickness_mm=3.2, modulus_kpa=150.0, poisson=0.42)
    assert fixture["lattice"] == dict(rows=19, cols=19, pitch_mm=1.0)
    assert fixture["library"]["name"] == "scikit-fem"
    assert "fe_reference.py" in fixture["generator"]["command"]
    names = [c["name"] for c in fixture["cases"]]
    assert names == ["sphere", "sphere-deep", "flat-punch", "flat-punch-sheared", "two-bumps"]
    for case in fixture["cases"]:
        assert set(case["markers"]) == {"ux_mm", "uy_mm", "w_mm", "pressure_kpa", "tau_x_kpa", "tau_y_kpa"}
        for values in case["markers"].values():
            assert len(values) == N and np.isfinite(values).all()
        truth = case["truth"]
        for key in ("contact_area_mm2", "force_N", "shear_x_N", "shear_y_N", "centroid_x_mm", "centroid_y_mm"):
            assert math.isfinite(truth[key])
        assert "contact_radius_mm" in truth
        assert case["mesh"]["nodes"] > 0 and case["mesh"]["elements"] > 0
        assert 0 <= case["mesh"]["converged_change_pct"] < 10
    assert FIXTURE.stat().st_size < 1_000_000


def test_fixture_is_internally_consistent(fixture):
    pitch = fixture["lattice"]["pitch_mm"]
    x = np.tile((np.arange(19) - 9) * pitch, 19)  # row-major: column varies fastest
    y = np.repeat((np.arange(19) - 9) * pitch, 19)
    for case in fixture["cases"]:
        m = {k: np.asarray(v) for k, v in case["markers"].items()}
        t = case["truth"]
        force = (m["pressure_kpa"] * pitch**2).sum() / 1000
        assert force == pytest.approx(t["force_N"], rel=0.02), case["name"]
        assert (m["tau_x_kpa"] * pitch**2).sum() / 1000 == pytest.approx(t["shear_x_N"], rel=0.02, abs=1e-5)
        assert (m["tau_y_kpa"] * pitch**2).sum() / 1000 == pytest.approx(t["shear_y_N"], rel=0.02, abs=1e-5)
        p = m["pressure_kpa"]
        assert (p * x).sum() / p.sum() == pytest.approx(t["centroid_x_mm"], abs=0.02)
        assert (p * y).sum() / p.sum() == pytest.approx(t["centroid_y_mm"], abs=0.02)
        assert p.min() > -0.05 * p.max()  # compressive contact (cell averages)
        ind = case["indenter"]
        if ind["shape"] == "sphere":
            # inside the contact (well inside, away from the interpolated edge) w is the sphere's
            depth = np.full(N, -np.inf)
            for s in ind["spheres"]:
                r2 = (x - s["center_mm"][0]) ** 2 + (y - s["center_mm"][1]) ** 2
                depth = np.maximum(depth, s["depth_mm"] - r2 / (2 * s["radius_mm"]))
            a_min = min(t["contact_radii_mm"])
            inside = depth > max(s["depth_mm"] - (0.7 * a_min) ** 2 / (2 * s["radius_mm"]) for s in ind["spheres"])
            assert inside.sum() >= 1
            # the FE surface field is bilinear between nodes (~0.1 mm apart), the sphere quadratic: the
            # interpolation at a marker sits up to (hx^2 + hy^2) / 8R below it, < 1 um here
            np.testing.assert_allclose(m["w_mm"][inside], depth[inside], atol=1e-3)
            assert (m["w_mm"] >= depth - 1e-3).all()  # no penetration anywhere
        else:
            r = np.hypot(x - ind["center_mm"][0], y - ind["center_mm"][1])
            face = r < ind["radius_mm"] - 0.1
            np.testing.assert_allclose(m["w_mm"][face], ind["depth_mm"], atol=1e-5)
            if ind.get("bonded"):
                np.testing.assert_allclose(m["ux_mm"][face], ind["shift_mm"][0], atol=1e-5)
                np.testing.assert_allclose(m["uy_mm"][face], ind["shift_mm"][1], atol=1e-5)
                assert t["shear_y_N"] / t["shear_x_N"] == pytest.approx(0.02 / 0.05, rel=1e-3)
            else:
                assert abs(t["shear_x_N"]) < 1e-6 and abs(t["shear_y_N"]) < 1e-6
