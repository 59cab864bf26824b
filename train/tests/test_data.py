import numpy as np
import pytest

from gelstereo_train.data import (DatasetError, dataset_tag, list_samples, median_nn_distance,
                                  nearest_neighbour_distances, read_markers_csv)
from gelstereo_train.tinydata import HEADER


def test_lists_both_views_of_every_frame(tiny_root):
    s = list_samples(tiny_root, "train")
    # 2 experiments x 2 frames x 2 views
    assert len(s) == 8
    assert {x.view for x in s} == {"left", "right"}
    assert all(x.points_px.shape[1] == 2 and len(x.points_px) > 20 for x in s)
    assert s[0].load().shape == (120, 160, 3)
    assert "seed=0" in dataset_tag(tiny_root, 8) and "images=8" in dataset_tag(tiny_root, 8)


def test_ground_truth_keeps_only_visible_rows_of_its_view(tmp_path):
    p = tmp_path / "markers.csv"
    p.write_text(
        HEADER + "\n"
        "0,0,0,1.0,2.0,3.0,4.0,,,,,,,tracked,1,0,0\n"
        "0,0,1,5.0,6.0,,,,,,,,,lost,1,0,1\n"
        "0,1,0,,,7.0,8.0,,,,,,,tracked,0,1,0\n"
    )
    f = read_markers_csv(p)[0]
    assert f["vis_left"].tolist() == [True, True, False]
    assert f["vis_right"].tolist() == [False, False, True]
    assert f["contact"].tolist() == [False, True, False]
    assert np.isnan(f["xy_right"][1]).all()


@pytest.mark.parametrize(
    "body, needle",
    [
        ("frame,row,col\n0,0,0\n", "header lacks"),
        (HEADER + "\n0,0,0,a,2,3,4,,,,,,,tracked,1,1,0\n", "expected numbers"),
        (HEADER + "\n0,0,0,1,2,3,4,,,,,,,tracked,yes,1,0\n", "visible_left"),
        ("", "empty file"),
    ],
)
def test_malformed_csv_names_file_and_field(tmp_path, body, needle):
    p = tmp_path / "markers.csv"
    p.write_text(body)
    with pytest.raises(DatasetError) as e:
        read_markers_csv(p)
    assert str(p) in str(e.value) and needle in str(e.value)


def test_missing_split_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match="split folder missing"):
        list_samples(tmp_path, "train")


def test_median_nn_distance_of_a_grid():
    g = np.stack(np.meshgrid(np.arange(5) * 7.0, np.arange(4) * 7.0), -1).reshape(-1, 2)
    assert median_nn_distance(g) == pytest.approx(7.0)
    assert np.isnan(median_nn_distance(g[:1]))


def _brute_force_nn(pts):
    d = np.sqrt(((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


@pytest.mark.parametrize("case", ["lattice", "uniform", "one column", "duplicates", "two", "clusters", "hidden"])
def test_nearest_neighbour_distances_are_the_brute_forces_exactly(case):
    """The sweep along x stops early; it must still find every point's nearest neighbour, on
    lattices whose columns share an x, on scattered points, on repeated points and on a column."""
    rng = np.random.default_rng(11)
    g = np.stack(np.meshgrid(np.arange(30) * 9.0, np.arange(25) * 9.0), -1).reshape(-1, 2)
    pts = {
        "lattice": g + rng.normal(0, 1.2, g.shape),
        "uniform": rng.uniform(0, 400, (700, 2)),
        "one column": np.stack([np.full(60, 3.0), rng.uniform(0, 500, 60)], 1),
        "duplicates": np.repeat(rng.uniform(0, 50, (40, 2)), 2, axis=0),
        "two": np.array([[0.0, 0.0], [3.0, 4.0]]),
        "clusters": np.concatenate([rng.normal(c, 2.0, (50, 2)) for c in ([0, 0], [300, 10], [40, 500])]),
        # the last point's nearest lies behind a tight cluster far off in y, which is all between them in x
        "hidden": np.array([[-0.5, 0.0], [0.0, 0.0], *[[0.6 + 0.01 * k, 1000 + 0.1 * k] for k in range(20)], [1.0, 0.0]]),
    }[case]
    assert np.array_equal(nearest_neighbour_distances(pts), _brute_force_nn(pts))
    assert median_nn_distance(pts) == float(np.median(_brute_force_nn(pts)))
