"""The decision rule of the BEV heads (``pretrain.evaluate.calibrate``) and the turning-pedestrian frame."""

from __future__ import annotations

import numpy as np

from pretrain.evaluate import calibrate, turning_pedestrian_frame


def test_calibrate_picks_the_best_threshold_and_scores_it_on_the_other_fold() -> None:
    th = (0.3, 0.5, 0.7)
    # 4 episodes x 3 thresholds x 4 targets; target 0 is best at 0.7 in every episode, target 1 at 0.3
    inter = np.zeros((4, 3, 4))
    union = np.full((4, 3, 4), 10.0)
    inter[:, :, 0] = [2, 4, 6]
    inter[:, :, 1] = [6, 4, 2]
    inter[:, :, 2:] = 5
    inter[1, :, 0] = [9, 1, 1]  # one odd episode (fold 1): at 0.3 its IoU is 0.9
    out = calibrate(inter, union, th, pos_weight=[1.0, 3.0, 1.0, 1.0])
    assert out["best_threshold"][0] == 0.7 and out["best_threshold"][1] == 0.3
    assert np.isclose(out["at_0.5"][0], (4 + 1 + 4 + 4) / 40)
    # fold 0 = episodes 0, 2 (threshold chosen on 1, 3: 0.3 → (2 + 2) / 20); fold 1 = 1, 3 (chosen on 0, 2: 0.7)
    assert out["cross_fit_thresholds"][0][0] == 0.3 and out["cross_fit_thresholds"][1][0] == 0.7
    assert np.isclose(out["cross_fitted"][0], (2 + 2 + 1 + 6) / 40)
    assert out["cross_fitted"][0] < out["best"][0]  # choosing on the scored episodes is optimistic
    assert out["bayes_threshold"][:2] == [0.5, 0.7]  # w / (1 + w) = 0.5, 0.75 → the grid's nearest


def test_turning_pedestrian_frame_finds_the_turn() -> None:
    from types import SimpleNamespace

    n, x, y = 6, 20, 20
    labels = np.zeros((n, 4, x, y), bool)
    for t in range(n):  # frame t: one blob now, at +0.5 s and +1.0 s; frame 4 turns 90 degrees, the others go straight
        labels[t, 1, 5:7, 5:7] = True
        labels[t, 2, 9:11, 5:7] = True
        labels[t, 3, 13:15, 5:7] = True
    labels[4, 3] = False
    labels[4, 3, 9:11, 9:11] = True
    store = SimpleNamespace(labels=labels, valid=np.ones((n, 4), bool))
    t, turn = turning_pedestrian_frame(store, [(0, n)], np.ones((x, y), bool), 0.1, stride=1)
    assert t == 4 and np.isclose(turn, 90.0)
    labels[:, 2, 0:2, 0:2] = True  # a second person everywhere: no frame shows one pedestrian
    assert turning_pedestrian_frame(store, [(0, n)], np.ones((x, y), bool), 0.1, stride=1) is None
