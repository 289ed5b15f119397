"""The SARL*-OM checkpoint the training and driver tests share (trained once per package)."""

from dataclasses import replace

import pytest
import yaml

from rl.baselines import sarl_om as S
from rl.stage import TrainConfig
from rl.teacher import CurriculumStage
from sim.env import SimConfig
from tests.rl.baselines.sarl_om.helpers import EMPTY_ROOM, RecordingLog


@pytest.fixture(scope="package")
def trained(tmp_path_factory):
    """A SARL*-OM imitation-trained on an empty room (40 short expert episodes, 60 epochs; no RL iteration: a
    handful of TD updates on so little data measurably unsettles the value, see the report)."""
    tmp = tmp_path_factory.mktemp("sarl_om")
    scene = tmp / "empty_room.yaml"
    scene.write_text(yaml.safe_dump(EMPTY_ROOM))
    sim_cfg = replace(SimConfig(), scene=str(scene), density=0.0, max_episode_s=5.0)
    cfg = TrainConfig(variant="sarl_om", sim=sim_cfg, workers=1, threads=1, progress=False, seed=0)
    cfg.teacher.curriculum = [CurriculumStage(until=1.0, scenes=[str(scene)], densities=[0.0])]
    cfg.teacher.bc_episodes = 40
    cfg.sarl_om = replace(S.Config(), il_epochs=60, rl_iterations=0, episodes_per_iter=2, train_batches=10,
                          target_update_episodes=2, checkpoint_every=1)

    log = RecordingLog()
    summary = S.train(cfg, tmp / "sarl_om", log)
    return tmp / "sarl_om", sim_cfg, summary, log
