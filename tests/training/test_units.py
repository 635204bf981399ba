"""Small pieces: sampler sharding and resume, LR schedule, RNG capture, CSV truncation, argv."""

# The legacy global numpy RNG is what the code under test saves and restores.
# ruff: noqa: NPY002

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from renderworld.training.api import hydra_argv
from renderworld.training.config import OptimizerConfig, SchedulerConfig
from renderworld.training.data import ShardedSampler
from renderworld.training.loggers import MetricLogger, truncate_metrics_csv
from renderworld.training.optim import (
    build_optimizer,
    build_scheduler,
    default_param_groups,
    lr_multiplier,
)
from renderworld.training.registry import Stage, get_stage, register_stage, sum_count
from renderworld.training.seed import get_rng_state, rng_isolated, seed_everything, set_rng_state


def test_shards_partition_the_single_process_order():
    one = ShardedSampler(10, seed=3)
    shards = [ShardedSampler(10, num_replicas=2, rank=r, seed=3) for r in range(2)]
    order = list(one)
    assert sorted(order) == list(range(10))
    # Global batch k of 2 ranks x batch 2 == batch k of one process x batch 4.
    assert sorted(list(shards[0])[:2] + list(shards[1])[:2]) == sorted(order[:4])
    one.set_epoch(1)
    assert list(one) != order  # reshuffled per epoch


def test_sampler_resumes_mid_epoch_and_validation_shards_do_not_repeat():
    s = ShardedSampler(11, seed=0)
    s.set_epoch(2)
    full = list(s)
    s.set_epoch(2, start=4)
    assert list(s) == full[4:] and len(s) == 7
    # Two ranks stopped after 4 samples (2 each) resume on three ranks with the rest of the order.
    two = [ShardedSampler(11, num_replicas=2, rank=r) for r in range(2)]
    for t in two:
        t.set_epoch(2)
    assert sorted(list(two[0])[:2] + list(two[1])[:2]) == sorted(full[:4])
    three = [ShardedSampler(11, num_replicas=3, rank=r) for r in range(3)]
    for t in three:
        t.set_epoch(2, start=4)
    assert sorted(i for t in three for i in t) == sorted(full[4:10])  # 7 left, 6 dealt evenly
    val = [
        ShardedSampler(11, num_replicas=3, rank=r, shuffle=False, drop_last=False) for r in range(3)
    ]
    seen = [i for v in val for i in v]
    assert sorted(seen) == list(range(11))
    with pytest.raises(ValueError, match="rank: expected 0 <= rank < 2, got 2"):
        ShardedSampler(4, num_replicas=2, rank=2)


def test_lr_schedule_warmup_then_cosine():
    cfg = SchedulerConfig(name="cosine", warmup_steps=4, min_lr_ratio=0.1)
    f = [lr_multiplier(s, cfg, 14) for s in range(15)]
    assert f[0] == pytest.approx(1 / 5) and f[3] == pytest.approx(4 / 5)
    assert f[4] == pytest.approx(1.0)
    assert f[9] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert f[14] == pytest.approx(0.1)
    assert all(a >= b for a, b in zip(f[4:], f[5:]))
    const = SchedulerConfig(name="constant", warmup_steps=0)
    assert lr_multiplier(100, const, 10) == 1.0


def test_param_groups_scale_the_rate_of_named_parameters_and_the_schedule_keeps_it():
    model = torch.nn.Sequential(torch.nn.Linear(2, 3), torch.nn.Linear(3, 1))
    cfg = OptimizerConfig(lr=0.01, weight_decay=0.1)
    plain = default_param_groups(model, cfg)
    assert [(len(g["params"]), g["weight_decay"], "lr" in g) for g in plain] == [
        (2, 0.1, False),
        (2, 0.0, False),
    ]
    assert default_param_groups(model, cfg, {}) == plain
    groups = default_param_groups(model, cfg, {"1.": 4.0})
    by_lr = {}
    for g in groups:
        by_lr.setdefault(g.get("lr", cfg.lr), []).extend(g["params"])
    assert {id(p) for p in by_lr[0.04]} == {id(p) for p in model[1].parameters()}
    assert {id(p) for p in by_lr[0.01]} == {id(p) for p in model[0].parameters()}
    opt = build_optimizer(model, cfg, groups)
    sched = build_scheduler(opt, SchedulerConfig(name="cosine", warmup_steps=0), 10)
    for _ in range(5):
        opt.step()
        sched.step()
    rates = sorted({g["lr"] for g in opt.param_groups})
    assert rates[1] == pytest.approx(4 * rates[0]) and rates[0] < 0.01  # decayed alike
    with pytest.raises(ValueError, match=r"lr_scales: prefix 'head\.' names no trainable"):
        default_param_groups(model, cfg, {"head.": 2.0})
    with pytest.raises(ValueError, match=r"lr_scales\['1\.'\]: expected a factor > 0"):
        default_param_groups(model, cfg, {"1.": 0.0})


def test_rng_state_round_trip_and_isolation():
    seed_everything(5)
    state = get_rng_state()
    a = (random.random(), np.random.rand(), torch.rand(1).item())
    set_rng_state(state)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == a
    set_rng_state(state)
    with rng_isolated():  # draws inside do not shift any stream outside
        random.random()
        np.random.rand(3)
        torch.rand(100)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == a
    with pytest.raises(TypeError, match="seed: expected an int"):
        seed_everything(1.5)  # type: ignore[arg-type]


def test_metrics_csv_truncation_drops_later_and_torn_rows(tmp_path):
    log = MetricLogger(tmp_path, tensorboard=False)
    for step in (1, 2, 3):
        log.log({"train/loss": 1.0 / step}, step)
    log.close()
    with open(tmp_path / "metrics.csv", "a") as f:
        f.write("4,0,train/lo")  # a kill mid-line
    assert truncate_metrics_csv(tmp_path / "metrics.csv", max_step=2) == 2
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines == ["step,epoch,key,value", "1,0,train/loss,1.0", "2,0,train/loss,0.5"]


def test_hydra_argv_maps_run_dir_and_quiets_other_ranks():
    argv = ["train.py", "stage=x", "run_dir=/r"]
    assert hydra_argv(argv, env={}) == [*argv, "hydra.run.dir=/r"]
    assert hydra_argv([*argv, "hydra.run.dir=/h"], env={})[-1] == "hydra.run.dir=/h"
    other = hydra_argv([*argv, "hydra.run.dir=/h"], env={"RANK": "1"})
    assert "hydra.run.dir=/h" not in other
    assert other[-3:] == ["hydra.run.dir=.", "hydra.output_subdir=null", "hydra/job_logging=stdout"]


def test_registry_and_default_metric_reduction():
    @register_stage("unit_dummy")
    class Dummy(Stage):
        def build_model(self, cfg):
            return torch.nn.Linear(1, 1)

        def build_datasets(self, cfg):
            return [], None

        def loss(self, model, batch):
            return torch.zeros(()), {}

        def evaluate(self, model, loader):
            return {}

    assert get_stage("unit_dummy") is Dummy and Dummy.name == "unit_dummy"
    with pytest.raises(ValueError, match="already registered"):

        @register_stage("unit_dummy")
        class Other(Dummy):
            pass

    with pytest.raises(TypeError, match="expected a Stage subclass"):
        register_stage("bad")(int)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"stage 'missing' is not registered \(no module given\)"):
        get_stage("missing")
    stage = Dummy(cfg=None)
    stats = {**sum_count("l", torch.tensor([1.0, 2.0, 6.0])), **sum_count("m", torch.ones(2))}
    assert stage.compute_metrics(stats) == {"l": 3.0, "m": 1.0}
    with pytest.raises(ValueError, match="cannot reduce 'confusion' by default"):
        stage.compute_metrics({"confusion": torch.eye(2)})
    with pytest.raises(ValueError, match="'l/sum' has no matching 'l/count'"):
        stage.compute_metrics({"l/sum": torch.tensor(1.0)})
