import sys

import pytest

from renderworld.pipeline.runner import PipelineError, Step, run_steps


def _steps(tmp_path, fail_second=False):
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    cfg = tmp_path / "cfg.yaml"
    if not cfg.exists():
        cfg.write_text("x: 1\n")
    write_a = f"import pathlib; p=pathlib.Path({str(a_out)!r}); p.mkdir(exist_ok=True); "
    write_a += "f=p/'n'; f.write_text(str(int(f.read_text())+1 if f.exists() else 1))"
    code_b = "raise SystemExit(3)" if fail_second else "print('b ran')"
    return [
        Step("a", "first", (sys.executable, "-c", write_a), a_out, inputs=(cfg,)),
        Step("b", "second", (sys.executable, "-c", code_b), b_out, depends_on=("a",)),
    ]


def test_second_run_skips_and_input_change_reruns(tmp_path):
    quiet = lambda *_: None  # noqa: E731
    r1 = run_steps(_steps(tmp_path), tmp_path / "logs", tmp_path, echo=quiet)
    assert [r.status for r in r1] == ["ran", "ran"]
    r2 = run_steps(_steps(tmp_path), tmp_path / "logs", tmp_path, echo=quiet)
    assert [r.status for r in r2] == ["skipped", "skipped"]
    assert (tmp_path / "a" / "n").read_text() == "1"
    (tmp_path / "cfg.yaml").write_text("x: 2\n")  # an input changed: a and its dependant re-run
    r3 = run_steps(_steps(tmp_path), tmp_path / "logs", tmp_path, echo=quiet)
    assert [r.status for r in r3] == ["ran", "ran"]
    # Outputs made from other inputs are cleared first, so the step starts over (n back to 1).
    assert (tmp_path / "a" / "n").read_text() == "1"
    assert "b ran" in (tmp_path / "logs" / "b.log").read_text()


def test_failed_step_keeps_earlier_work_and_retries(tmp_path):
    quiet = lambda *_: None  # noqa: E731
    with pytest.raises(PipelineError, match=r"step 'b' failed with exit code 3 .*b.log"):
        run_steps(_steps(tmp_path, fail_second=True), tmp_path / "logs", tmp_path, echo=quiet)
    r = run_steps(_steps(tmp_path), tmp_path / "logs", tmp_path, echo=quiet)
    assert [x.status for x in r] == ["skipped", "ran"]


def test_unknown_dependency_is_rejected(tmp_path):
    step = Step("x", "x", (sys.executable, "-c", "pass"), tmp_path / "x", depends_on=("nope",))
    with pytest.raises(ValueError, match="depends_on names unknown step 'nope'"):
        run_steps([step], tmp_path / "logs", tmp_path, echo=lambda *_: None)


def test_changed_inputs_start_over_instead_of_resuming(tmp_path):
    out, cfg = tmp_path / "t", tmp_path / "cfg.yaml"
    cfg.write_text("x: 1\n")
    code = (
        "import pathlib, sys; o=pathlib.Path(sys.argv[1]); o.mkdir(exist_ok=True);"
        "(o/'args').write_text(' '.join(sys.argv[2:])); (o/'last.pt').write_text('x')"
    )

    def step():
        return Step(
            "t", "train", (sys.executable, "-c", code, str(out)), out, inputs=(cfg,),
            resume_args=("resume=true",), resume_marker=out / "last.pt",
        )  # fmt: skip

    quiet = lambda *_: None  # noqa: E731
    run_steps([step()], tmp_path / "logs", tmp_path, echo=quiet)
    assert (out / "args").read_text() == ""
    cfg.write_text("x: 2\n")  # finished before, inputs changed: fresh run, no resume
    run_steps([step()], tmp_path / "logs", tmp_path, echo=quiet)
    assert (out / "args").read_text() == ""
    (out / ".step-done.json").unlink()  # interrupted (no stamp) with a checkpoint: resume
    run_steps([step()], tmp_path / "logs", tmp_path, echo=quiet)
    assert (out / "args").read_text() == "resume=true"


def test_main_job_steps_form_a_resumable_dependency_chain(tmp_path):
    from pathlib import Path

    from omegaconf import OmegaConf

    from renderworld.pipeline.main_job import main_job_steps

    repo = Path(__file__).resolve().parents[2]
    cfg = OmegaConf.load(repo / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root = str(tmp_path / "out"), str(tmp_path / "data")
    steps = main_job_steps(cfg, repo)
    names = [s.name for s in steps]
    assert len(set(names)) == len(names)
    assert len({s.out_dir for s in steps}) == len(steps)
    for i, s in enumerate(steps):
        assert set(s.depends_on) <= set(names[:i]), s.name  # upstream steps run first
        if s.command[1] == "tools/train.py":  # every training step resumes from its last.pt
            assert s.resume_marker == s.out_dir / "checkpoints" / "last.pt"
            # ... and a later step evaluates its checkpoint
            ckpt = s.out_dir / "checkpoints" / "last.pt"
            evals = [e for e in steps[i + 1 :] if e.command[1] == "tools/eval.py"]
            assert any(str(ckpt) in " ".join(e.command) for e in evals), s.name
    for required in ("fixtures", "infos", "tokenizer", "img2occ", "pseudo_labels"):
        assert required in names
    # On a CPU every step up to the last world model's runs on one core beside another: Img2Occ
    # and the Camera chain behind it on one, the scenario data, the tokenizer and the 3D-Occ
    # world model on the other; the closing evaluations have the machine.
    data = {"fixtures", "infos", "scenario_data", "scenario_infos", "interaction_data",
            "interaction_infos"}  # fmt: skip
    camera = {"img2occ", "img2occ_eval", "pseudo_labels", "tokenizer_camera",
              "world_model_camera"}  # fmt: skip
    gt = {"tokenizer", "tokenizer_eval", "world_model", "world_model_interactions"}
    shared = {s.name for s in steps if s.cores is not None}
    assert shared == data | camera | gt
    assert all(s.cores == 1 for s in steps if s.name in shared)
    # The scheduler never lets a step pass one waiting for the whole machine: none is listed
    # before the last one-core step, so the two chains keep both cores busy to their ends.
    last_shared = max(names.index(n) for n in shared)
    assert all(s.cores == 1 for s in steps[:last_shared]), [s.name for s in steps[:last_shared]]
    for n in (camera | gt) - {"pseudo_labels"}:
        assert "trainer.num_threads=1" in steps[names.index(n)].command, n
    assert "threads=1" in steps[names.index("pseudo_labels")].command
    # Img2Occ is listed right after the fixture's conversion, so it starts once the infos are
    # written (the scheduler never lets a step pass one waiting for cores).
    assert names.index("img2occ") == names.index("infos") + 1
    assert set(steps[names.index("img2occ")].depends_on) == {"infos"}
    # On a GPU (the paper family) every training has the machine to itself, threads untouched.
    cfg.experiments = "paper"
    gpu = main_job_steps(cfg, repo)
    assert {s.name for s in gpu if s.cores is not None} <= data
    assert not any("trainer.num_threads=1" in s.command or "threads=1" in s.command for s in gpu)
    assert not any(a.startswith("init_from=") for s in gpu for a in s.command)
    cfg.experiments = "mini"
    # One world-model evaluation after both trainings: one table with both settings.
    wm = steps[names.index("world_model_eval")]
    assert names.index("world_model_eval") > names.index("world_model_camera")
    assert set(wm.depends_on) == {
        "world_model", "tokenizer_camera", "world_model_camera", "pseudo_labels"
    }  # fmt: skip
    out = tmp_path / "out"
    args = dict(a.split("=", 1) for a in wm.command[2:])
    assert args["pseudo_labels"] == str(out / "pseudo_labels")
    assert args["camera_ckpt"].endswith("world_model_camera/checkpoints/last.pt")
    assert args["ckpt"].endswith("world_model/checkpoints/last.pt")
    assert args["stage.tokenizer_ckpt"] == str(out / "tokenizer" / "checkpoints" / "last.pt")
    cam_tok = str(out / "tokenizer_camera" / "checkpoints" / "last.pt")
    assert args["camera_tokenizer_ckpt"] == cam_tok
    assert "world_model_camera_eval" not in names
    # The Camera setting's own tokenizer: the 3D-Occ one fine-tuned on the pseudo labels, read
    # by its world model, the 3D-Occ one fine-tuned on the same labels.
    tc = steps[names.index("tokenizer_camera")]
    assert names.index("pseudo_labels") < names.index("tokenizer_camera")
    assert names.index("tokenizer_camera") < names.index("world_model_camera")
    assert set(tc.depends_on) == {"pseudo_labels", "tokenizer"}
    targs = dict(a.split("=", 1) for a in tc.command[2:])
    assert targs["experiment"] == "tokenizer_camera_mini"
    assert targs["stage.occ_root"] == str(out / "pseudo_labels")
    assert targs["init_from"] == str(out / "tokenizer" / "checkpoints" / "last.pt")
    assert "tokenizer_camera_eval" not in names
    wmc = steps[names.index("world_model_camera")]
    assert set(wmc.depends_on) == {"tokenizer_camera", "pseudo_labels", "world_model"}
    cargs = dict(a.split("=", 1) for a in wmc.command[2:])
    assert cargs["experiment"] == "world_model_camera_mini"
    assert cargs["stage.tokenizer_ckpt"] == cam_tok
    assert cargs["stage.occ_root"] == str(out / "pseudo_labels")
    assert cargs["init_from"] == str(out / "world_model" / "checkpoints" / "last.pt")
    gt = dict(a.split("=", 1) for a in steps[names.index("world_model")].command[2:])
    assert gt["stage.tokenizer_ckpt"] == str(out / "tokenizer" / "checkpoints" / "last.pt")
    # The planner of the world model the job trained (pose_warp in world_model_mini).
    planner = steps[names.index("planner")]
    assert planner.command[1] == "tools/export_planner.py"
    assert set(planner.depends_on) == {"tokenizer", "world_model"}
    pargs = dict(a.split("=", 1) for a in planner.command[2:])
    assert pargs == {
        "world_model_ckpt": str(out / "world_model" / "checkpoints" / "last.pt"),
        "tokenizer_ckpt": str(out / "tokenizer" / "checkpoints" / "last.pt"),
        "out": str(out / "planner" / "planner.pt"),
    }
    # Scenario data: the library (occupancy only) feeds the 3D-Occ world model's training; the
    # held-out interaction split is scored with the same checkpoints.
    lib, inter = tmp_path / "sim_scenarios", tmp_path / "sim_interactions"
    sim = {s.name: s for s in steps if s.command[1] == "tools/make_fixtures.py"}
    assert f"out={lib}" in sim["scenario_data"].command
    assert f"out={inter}" in sim["interaction_data"].command
    assert all("mode=occupancy" in sim[n].command for n in ("scenario_data", "interaction_data"))
    assert "labels=false" in steps[names.index("scenario_infos")].command
    assert "scenario_infos" in steps[names.index("world_model")].depends_on
    assert gt["stage.extra_train_roots"] == f"[{lib}]"
    assert "stage.extra_train_roots" not in cargs  # the Camera setting trains on its own labels
    ia = steps[names.index("world_model_interactions")]
    iargs = dict(a.split("=", 1) for a in ia.command[2:])
    assert iargs["dataset.data_root"] == str(inter) and iargs["ckpt"] == args["ckpt"]
    assert set(ia.depends_on) == {"world_model", "interaction_infos"}
    cfg.scenarios = False
    assert not {"scenario_data", "world_model_interactions"} & {
        s.name for s in main_job_steps(cfg, repo)
    }


def test_real_data_main_job_runs_the_paper_experiments_without_simulating(tmp_path):
    from pathlib import Path

    from omegaconf import OmegaConf

    from renderworld.pipeline.main_job import main_job_steps

    repo = Path(__file__).resolve().parents[2]
    cfg = OmegaConf.load(repo / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root = str(tmp_path / "out"), str(tmp_path / "nuscenes")
    cfg.preset, cfg.version, cfg.experiments = None, "v1.0-trainval", "paper"
    steps = main_job_steps(cfg, repo)
    names = [s.name for s in steps]
    assert "fixtures" not in names and names[0] == "infos" and steps[0].depends_on == ()
    assert "scenario_data" not in names  # the scenario library is the mini family's
    assert "version=v1.0-trainval" in steps[0].command
    for s in steps[1:]:
        assert set(s.depends_on) <= set(names[: names.index(s.name)]), s.name
    args = {s.name: dict(a.split("=", 1) for a in s.command[2:]) for s in steps[1:]}
    want = {
        "tokenizer": "paper_tokenizer",
        "img2occ": "paper_img2occ",
        "world_model": "paper_world_model",
        "tokenizer_camera": "paper_tokenizer",
        "world_model_camera": "paper_camera",
        "world_model_eval": "paper_world_model",
    }
    for name, experiment in want.items():
        assert args[name]["experiment"] == experiment, name
        assert args[name]["dataset.version"] == "v1.0-trainval", name
    # Pseudo labels exported on the GPU Img2Occ trained on, from the real data's version.
    assert args["pseudo_labels"]["device"] == "cuda"
    assert args["pseudo_labels"]["version"] == "v1.0-trainval"
    cfg.experiments = "huge"
    with pytest.raises(ValueError, match=r"experiments: expected one of \['mini', 'paper'\]"):
        main_job_steps(cfg, repo)


@pytest.mark.parametrize("family", ["mini", "paper"])
def test_no_main_job_step_reads_a_checkpoint_chosen_on_the_reported_split(
    tmp_path, monkeypatch, family
):
    """best.pt is picked on the validation split the report scores: every step that reads a
    checkpoint (evaluations, downstream training, pseudo labels, planner, viewer) reads
    last.pt, and the report's figure reads the same file."""
    from pathlib import Path

    from omegaconf import OmegaConf

    import renderworld.viewer
    from renderworld.pipeline.main_job import main_job_steps
    from renderworld.viewer.job import JOB_CHECKPOINTS

    monkeypatch.setattr(renderworld.viewer, "rerun_available", lambda: True)
    repo = Path(__file__).resolve().parents[2]
    cfg = OmegaConf.load(repo / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root, cfg.experiments = str(tmp_path / "out"), str(tmp_path / "d"), family
    steps = main_job_steps(cfg, repo)
    args = [(s.name, *a.split("=", 1)) for s in steps for a in s.command[2:] if "=" in a]
    read = [(name, value) for name, key, value in args if key.endswith("ckpt")]
    readers = {name for name, _ in read}
    assert {"tokenizer_eval", "img2occ_eval", "world_model_eval", "pseudo_labels"} <= readers
    assert {"world_model", "world_model_camera", "planner"} <= readers
    if family == "mini":
        assert {"viewer", "world_model_interactions"} <= readers
    assert all(v.startswith(str(tmp_path / "out")) for _, v in read), read
    assert all(v.endswith("/checkpoints/last.pt") for _, v in read), read
    assert all(v.endswith("/checkpoints/last.pt") for v in JOB_CHECKPOINTS.values())


def test_closed_loop_code_leaves_the_simulated_data_up_to_date(tmp_path):
    """Changing the closed loop (planners, scores) re-drives the scenes but re-simulates and
    retrains nothing; changing the simulator re-simulates every dataset."""
    import shutil
    from pathlib import Path

    from omegaconf import OmegaConf

    from renderworld.pipeline.main_job import main_job_steps
    from renderworld.pipeline.runner import fingerprint_paths

    real = Path(__file__).resolve().parents[2]
    repo = tmp_path / "repo"
    shutil.copytree(
        real / "renderworld", repo / "renderworld", ignore=shutil.ignore_patterns("__pycache__")
    )
    shutil.copytree(real / "configs", repo / "configs")
    cfg = OmegaConf.load(repo / "configs" / "pipeline.yaml")
    cfg.out, cfg.data_root = str(tmp_path / "out"), str(tmp_path / "data")

    def prints():
        return {s.name: fingerprint_paths(s.inputs) for s in main_job_steps(cfg, repo)}

    before = prints()
    with open(repo / "renderworld" / "sim" / "closed_loop" / "planners.py", "a") as f:
        f.write("\n# changed\n")
    after = prints()
    changed = {n for n in before if before[n] != after[n]}
    assert changed == {"closed_loop"}
    with open(repo / "renderworld" / "sim" / "scene.py", "a") as f:
        f.write("\n# changed\n")
    resimulated = {n for n, v in prints().items() if v != after[n]}
    assert {"fixtures", "scenario_data", "interaction_data", "closed_loop"} <= resimulated
