import numpy as np
import torch

from gelstereo_train.loss import build_targets, distillation_loss, marknet_loss


def test_assignment_cell_then_x_order_and_overflow():
    # cell size 8: three markers in cell (0, 0), one in cell (1, 2)
    pts = np.array([[6.0, 1.0], [2.0, 5.0], [4.0, 4.0], [20.0, 9.0]], np.float32)
    tgt, mask, dropped = build_targets([pts], 4, 4, 8, 2)
    assert dropped == 1  # the third marker of cell (0, 0) does not fit m = 2
    assert mask[0, 0, 0].tolist() == [True, True]
    assert tgt[0, 0, 0, 0].tolist() == [2.0, 5.0] and tgt[0, 0, 0, 1].tolist() == [4.0, 4.0]
    assert mask[0, 1, 2].tolist() == [True, False] and tgt[0, 1, 2, 0].tolist() == [20.0, 9.0]
    assert int(mask.sum()) == 3


def test_loss_is_small_at_the_targets_and_large_elsewhere():
    pts = np.array([[3.0, 5.0], [13.0, 2.5]], np.float32)
    tgt, mask, _ = build_targets([pts], 2, 2, 8, 1)
    raw = torch.full((1, 2, 2, 1, 3), -12.0)
    for (x, y) in pts:
        gx, gy = int(x // 8), int(y // 8)
        fx, fy = x / 8 - gx, y / 8 - gy
        raw[0, gy, gx, 0] = torch.tensor([np.log(fx / (1 - fx)), np.log(fy / (1 - fy)), 12.0])
    total, conf, dist, mean_d = marknet_loss(raw, tgt, mask, 8)
    assert float(mean_d) < 1e-3 and float(total) < 1e-3
    raw2 = raw.clone()
    raw2[..., 0] += 1.0
    assert float(marknet_loss(raw2, tgt, mask, 8)[3]) > 0.5


def test_distillation_loss_is_zero_for_a_copy_of_the_teacher_and_grows_with_the_difference():
    torch.manual_seed(0)
    teacher = torch.randn(2, 4, 4, 3, 3) * 3.0
    total, conf, dist = distillation_loss(teacher.clone(), teacher, 8)
    assert abs(float(conf)) < 1e-5 and float(dist) < 1e-3
    moved = teacher.clone()
    moved[..., 0] += 1.0  # every slot's x moves
    assert float(distillation_loss(moved, teacher, 8)[2]) > 0.5
    unsure = teacher.clone()
    unsure[..., 2] -= 2.0
    assert float(distillation_loss(unsure, teacher, 8)[1]) > 0.05


def test_distillation_ignores_positions_of_slots_the_teacher_calls_empty():
    teacher = torch.zeros(1, 2, 2, 1, 3)
    teacher[..., 2] = -8.0  # confidence 0.0003 everywhere: no marker
    moved = teacher.clone()
    moved[..., :2] += 3.0
    assert float(distillation_loss(moved, teacher, 8)[2]) == 0.0
    teacher[0, 0, 0, 0, 2] = 8.0  # one sure slot: its position counts
    moved = teacher.clone()
    moved[0, 0, 0, 0, :2] += 3.0
    assert float(distillation_loss(moved, teacher, 8)[2]) > 1.0
