"""The command derived from the GT future, and the model's row with that command withheld."""

from __future__ import annotations

import copy
import csv
import io

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from renderworld.constants import COMMANDS
from renderworld.training.stages.world_model import WorldModelStage
from renderworld.training.stages.world_model.report import HISTORY_COMMAND, report_tables
from renderworld.world import command_indices, constant_turn_rate_poses

from . import test_world_model_stage as base
from .conftest import compose_cfg

# The stage tests' module fixtures: the tiny fixture, its tiny tokenizer and the overrides.
converted, tokenizer_ckpt, wm_overrides = base.converted, base.tokenizer_ckpt, base.wm_overrides


def test_command_indices_apply_the_command_rule_to_each_trajectory():
    hist = torch.tensor(
        [
            [[-10.0, 0.0, 0.0], [-5.0, 0.0, 0.0], [0.0, 0.0, 0.0]],  # straight on
            [[-9.8, -1.0, -0.2], [-5.0, -0.25, -0.1], [0.0, 0.0, 0.0]],  # turning left
            [[-9.8, 1.0, 0.2], [-5.0, 0.25, 0.1], [0.0, 0.0, 0.0]],  # turning right
        ],
        dtype=torch.float64,
    )
    ctr = constant_turn_rate_poses(hist, 6)[..., :2]
    got = [COMMANDS[i] for i in command_indices(ctr.numpy())]
    assert got == ["straight", "left", "right"]
    with pytest.raises(ValueError, match=r"trajectories: expected \[B, S, 2\]"):
        command_indices(np.zeros((6, 2)))


def _stage(wm_overrides, tmp_path, kind):
    cfg = compose_cfg([*wm_overrides, f"stage.forecaster={kind}", f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    _, val_set = stage.build_datasets(cfg)
    model = stage.build_model(cfg).eval()
    torch.manual_seed(0)
    with torch.no_grad():  # a model whose plan depends on the command (heads start at zero)
        for p in model.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return stage, model, val_set


@pytest.mark.parametrize("kind", ["tokens", "pose_warp"])
def test_the_history_command_row_never_reads_the_gt_command(wm_overrides, tmp_path, kind):
    stage, model, val_set = _stage(wm_overrides, tmp_path, kind)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    setting = stage.eval_settings[0]
    held = command_indices(constant_turn_rate_poses(batch["history_poses"].double(), 4)[..., :2])
    runs = {}
    for c in range(len(COMMANDS)):  # every GT command: the history-command row stays the same
        other = copy.deepcopy(batch)
        other["command"] = torch.full_like(batch["command"], c)
        runs[c] = stage.forecast(model, other, setting, None)
    fc0, traj0 = runs[0]
    for fc, traj in runs.values():
        assert torch.equal(fc[HISTORY_COMMAND], fc0[HISTORY_COMMAND])
        assert torch.equal(traj[HISTORY_COMMAND], traj0[HISTORY_COMMAND])
    # ... while the model row reads it (the check above could not pass by ignoring commands),
    assert any(not torch.equal(traj["model"], traj0["model"]) for _, traj in runs.values())
    # ... nor the GT future,
    future = copy.deepcopy(batch)
    g = torch.Generator().manual_seed(0)
    for key in ("future_poses", "future_traj"):
        future[key] = torch.randn(future[key].shape, generator=g) * 10
    future["occ"][:, base.HISTORY :] = 0
    fc, traj = stage.forecast(model, future, setting, None)
    assert torch.equal(fc[HISTORY_COMMAND], fc0[HISTORY_COMMAND])
    assert torch.equal(traj[HISTORY_COMMAND], traj0[HISTORY_COMMAND])
    # ... and the row is the same model given the history's command.
    mine = copy.deepcopy(batch)
    mine["command"] = torch.as_tensor(held)
    fc, traj = stage.forecast(model, mine, setting, None)
    assert torch.equal(fc["model"], fc0[HISTORY_COMMAND])
    assert torch.equal(traj["model"], traj0[HISTORY_COMMAND])


def test_the_table_has_the_history_command_row_and_says_where_the_command_comes_from():
    metrics = {}
    for m, v in (("model", 0.3), (HISTORY_COMMAND, 0.2), ("cv_traj", None)):
        for h in ("1s", "avg"):
            if v is not None:
                metrics[f"val/{m}/miou_{h}"] = v
            metrics[f"val/{m}/l2_at_horizon_{h}"] = 1.0 if v is None else v * 4
    text, md, csv_text = report_tables(metrics, (1.0,), ["header"])
    rows = {r["method"]: r for r in csv.DictReader(io.StringIO(csv_text))}
    assert float(rows["model, command from history"]["miou_1s_pct"]) == pytest.approx(20.0)
    assert float(rows["model"]["miou_1s_pct"]) == pytest.approx(30.0)
    assert "| 3D-Occ | model, command from history | 20.00 |" in md
    for out in (text, md):
        assert "derived from the ground-truth future" in out
        assert "command from history = the same model" in out
