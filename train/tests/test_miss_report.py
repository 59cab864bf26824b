"""`scripts/miss_report.py`: each missed marker lands in the class of what lies near it."""

import numpy as np


def test_each_miss_is_classed_by_what_lies_near_it(script):
    m = script("miss_report")
    pitch = 20.0
    gt = np.array([(x, y) for y in range(40, 201, 20) for x in range(40, 201, 20)], np.float64)
    missed = {"off": (100.0, 100.0), "dropped": (140.0, 140.0), "unsure": (60.0, 160.0), "none": (180.0, 80.0)}
    corner = (40.0, 40.0)  # 2 pitches from the image's left and top edges: no border marker
    far = [tuple(p) for p in gt if tuple(p) not in missed.values() and tuple(p) != corner]
    det = np.array(far + [(missed["off"][0] + 0.4 * pitch, missed["off"][1])])
    candidates = np.array([
        (*missed["dropped"], 0.95),
        (missed["unsure"][0] + 2.0, missed["unsure"][1], 0.25),
        (missed["none"][0] + 0.5 * pitch, missed["none"][1], 0.9),  # too far to be its find
        (*corner, 0.8),
    ])
    classes = m.classify_misses(gt, det, candidates, (240, 240))
    # The misses in the order of `gt`.
    order = [i for i, p in enumerate(gt) if tuple(p) in missed.values() or tuple(p) == corner]
    got = dict(zip((tuple(gt[i]) for i in order), classes))
    assert got[missed["off"]] == m.CLASSES.index("placed off")
    assert got[missed["dropped"]] == m.CLASSES.index("sure, dropped")
    assert got[missed["unsure"]] == m.CLASSES.index("unsure")
    assert got[missed["none"]] == m.CLASSES.index("none")
    assert got[corner] == m.CLASSES.index("sure, dropped")


def test_a_sure_candidate_at_the_border_is_its_own_class(script):
    m = script("miss_report")
    gt = np.array([(x, y) for y in range(5, 120, 20) for x in range(25, 140, 20)], np.float64)
    det = gt[1:]
    candidates = np.array([(*gt[0], 0.9)])
    assert m.classify_misses(gt, det, candidates, (160, 160)) == [m.CLASSES.index("sure, at the border")]
