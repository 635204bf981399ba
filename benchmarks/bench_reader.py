"""Reader benchmark: load time and peak memory at v1.0-trainval size, beside the devkit.

Builds (once, cached) a synthetic nuScenes table set the size of v1.0-trainval — 850 scenes,
~34k samples, ~2.6M sample_data and ego_pose rows, ~1.2M annotations, lidarseg records and
files — then, each in a fresh process and in the same run:

* ``renderworld``: ``NuScenesReader(root, version).load_all()`` (every table parsed, every
  reference and prev/next chain checked, keyframe index built);
* ``devkit``: the official ``NuScenes(version, dataroot)`` (in its own numpy<2 venv).

Prints wall time (median over ``--repeat``) and peak RSS for both and their ratio.

Usage::

    python benchmarks/bench_reader.py [--scale 1.0] [--repeat 3] [--root .cache/bench-trainval]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import orjson

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from renderworld.constants import CAMERA_NAMES, LIDARSEG_CLASSES  # noqa: E402

VERSION = "v1.0-trainval"
RADARS = ("RADAR_FRONT", "RADAR_FRONT_LEFT", "RADAR_FRONT_RIGHT", "RADAR_BACK_LEFT",
          "RADAR_BACK_RIGHT")  # fmt: skip
CHANNELS = (*CAMERA_NAMES, "LIDAR_TOP", *RADARS)


def tok(kind: str, i: int) -> str:
    return f"{kind}{i:x}".rjust(32, "0")


def build(root: Path, scale: float) -> dict:
    """Write the synthetic trainval-sized tables (skipped if already built at this scale)."""
    stamp = root / "built.json"
    if stamp.exists() and json.loads(stamp.read_text()).get("scale") == scale:
        return json.loads(stamp.read_text())
    t0 = time.perf_counter()
    vdir = root / VERSION
    vdir.mkdir(parents=True, exist_ok=True)
    n_scenes = max(2, round(850 * scale))
    per_scene = 40
    # Sweeps per keyframe so that sample_data totals ~2.6M: cams 12 Hz, lidar 20 Hz, radar 13 Hz.
    sweeps = {**{c: 6 for c in CAMERA_NAMES}, "LIDAR_TOP": 10, **{r: 6 for r in RADARS}}
    sensors = [
        {"token": tok("sen", i), "channel": c, "modality": c.split("_")[0].lower()}
        for i, c in enumerate(CHANNELS)
    ]
    logs, maps, scenes, samples, sds, poses, anns, insts, calibs, lsegs = ([] for _ in range(10))
    cats = [{"token": tok("cat", i), "name": n, "description": n, "index": i}
            for i, n in enumerate(LIDARSEG_CLASSES)]  # fmt: skip
    sd_i = ann_i = 0
    for s in range(n_scenes):
        logs.append({"token": tok("log", s), "logfile": f"n015-{s}", "vehicle": "n015",
                     "date_captured": "2018-07-24", "location": "boston-seaport"})  # fmt: skip
        cs_tok = {}
        for i, c in enumerate(CHANNELS):
            cs_tok[c] = tok("cs", s * 100 + i)
            calibs.append({"token": cs_tok[c], "sensor_token": sensors[i]["token"],
                           "translation": [1.0, 0.0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5],
                           "camera_intrinsic": [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5],
                                                [0.0, 0.0, 1.0]] if c.startswith("CAM") else []})  # fmt: skip
        first = len(samples)
        last_sd: dict[str, dict] = {}
        n_inst = 40
        inst0 = len(insts)
        inst_prev: dict[int, dict] = {}
        for k in range(per_scene):
            ts = 1_500_000_000_000_000 + s * 10**8 + k * 500_000
            st = tok("smp", len(samples))
            samples.append({"token": st, "timestamp": ts, "scene_token": tok("scn", s),
                            "prev": samples[-1]["token"] if k else "", "next": ""})  # fmt: skip
            if k:
                samples[-2]["next"] = st
            for c in CHANNELS:
                for w in range(sweeps[c]):
                    t = tok("sd", sd_i)
                    sd_i += 1
                    ext = "jpg" if c.startswith("CAM") else "pcd.bin" if c == "LIDAR_TOP" else "pcd"
                    folder = "samples" if w == 0 else "sweeps"
                    rec = {"token": t, "sample_token": st, "ego_pose_token": t,
                           "calibrated_sensor_token": cs_tok[c],
                           "filename": f"{folder}/{c}/n015-{s}__{c}__{ts + w}.{ext}",
                           "fileformat": ext.split(".")[0], "width": 1600, "height": 900,
                           "timestamp": ts + w * 1000, "is_key_frame": w == 0,
                           "prev": last_sd[c]["token"] if c in last_sd else "", "next": ""}  # fmt: skip
                    if c in last_sd:
                        last_sd[c]["next"] = t
                    last_sd[c] = rec
                    sds.append(rec)
                    poses.append({"token": t, "translation": [float(k), float(s), 0.0],
                                  "rotation": [1.0, 0.0, 0.0, 0.0], "timestamp": ts + w * 1000})  # fmt: skip
                    if c == "LIDAR_TOP" and w == 0:
                        lsegs.append({"token": t, "sample_data_token": t,
                                      "filename": f"lidarseg/{VERSION}/{t}_lidarseg.bin"})  # fmt: skip
            for j in range(n_inst if k < per_scene - 5 else 25):  # ~1.2M annotations in all
                at = tok("ann", ann_i)
                ann_i += 1
                rec = {"token": at, "sample_token": st, "instance_token": tok("ins", inst0 + j),
                       "attribute_tokens": [], "visibility_token": "4",
                       "translation": [float(j), 2.0, 1.0], "size": [1.9, 4.5, 1.6],
                       "rotation": [1.0, 0.0, 0.0, 0.0], "num_lidar_pts": 5, "num_radar_pts": 0,
                       "prev": inst_prev[j]["token"] if j in inst_prev else "", "next": ""}  # fmt: skip
                if j in inst_prev:
                    inst_prev[j]["next"] = at
                inst_prev[j] = rec
                anns.append(rec)
        for j in range(n_inst):
            seq = [a for a in (inst_prev[j],)]
            first_ann = next(a for a in anns[-(per_scene * n_inst):]
                             if a["instance_token"] == tok("ins", inst0 + j))  # fmt: skip
            insts.append({"token": tok("ins", inst0 + j), "category_token": cats[17]["token"],
                          "nbr_annotations": 0, "first_annotation_token": first_ann["token"],
                          "last_annotation_token": seq[-1]["token"]})  # fmt: skip
        scenes.append({"token": tok("scn", s), "name": f"scene-{s:04d}", "description": "",
                       "log_token": tok("log", s), "nbr_samples": per_scene,
                       "first_sample_token": samples[first]["token"],
                       "last_sample_token": samples[-1]["token"]})  # fmt: skip
    maps.append({"token": tok("map", 0), "log_tokens": [x["token"] for x in logs],
                 "category": "semantic_prior", "filename": f"maps/{tok('map', 0)}.png"})  # fmt: skip
    tables = {
        "category": cats, "attribute": [], "visibility": [
            {"token": str(i), "level": f"v{i}", "description": ""} for i in range(1, 5)],
        "instance": insts, "sensor": sensors, "calibrated_sensor": calibs, "ego_pose": poses,
        "log": logs, "scene": scenes, "sample": samples, "sample_data": sds,
        "sample_annotation": anns, "map": maps, "lidarseg": lsegs,
    }  # fmt: skip
    for name, recs in tables.items():
        (vdir / f"{name}.json").write_bytes(orjson.dumps(recs))
    (root / "maps").mkdir(exist_ok=True)
    from PIL import Image

    Image.new("L", (8, 8), 255).save(root / maps[0]["filename"])
    ldir = root / "lidarseg" / VERSION
    ldir.mkdir(parents=True, exist_ok=True)
    for rec in lsegs:
        (root / rec["filename"]).touch()
    info = {"scale": scale, "counts": {k: len(v) for k, v in tables.items()},
            "bytes": sum(p.stat().st_size for p in vdir.glob("*.json")),
            "build_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    stamp.write_text(json.dumps(info))
    return info


OURS = """
import resource, sys, time
sys.path.insert(0, {repo!r})
t0 = time.perf_counter()
from renderworld.data import NuScenesReader
r = NuScenesReader({root!r}, {version!r}).load_all()
dt = time.perf_counter() - t0
print(dt, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""
DEVKIT = """
import resource, sys, time
t0 = time.perf_counter()
from nuscenes.nuscenes import NuScenes
n = NuScenes({version!r}, {root!r}, verbose=False)
dt = time.perf_counter() - t0
print(dt, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def run(python: str, code: str) -> tuple[float, float]:
    env = {"PATH": "/usr/bin:/bin", "HOME": str(Path.home())}
    out = subprocess.run([python, "-c", code], capture_output=True, text=True, env=env)
    if out.returncode:
        raise RuntimeError(out.stderr[-3000:])
    dt, rss_kb = out.stdout.split()[-2:]
    return float(dt), float(rss_kb) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="fraction of trainval size")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--root", type=Path, default=REPO / ".cache" / "bench-trainval")
    ap.add_argument("--no-devkit", action="store_true")
    args = ap.parse_args()
    info = build(args.root / f"scale{args.scale:g}", args.scale)
    root = str(args.root / f"scale{args.scale:g}")
    print(f"tables: {info['counts']}  ({info['bytes'] / 2**30:.2f} GiB JSON)")
    rows = {"renderworld": (sys.executable, OURS)}
    if not args.no_devkit:
        sys.path.insert(0, str(REPO))
        from tests.devkit_oracle import devkit_python

        rows["devkit"] = (str(devkit_python()), DEVKIT)
    results: dict[str, list[tuple[float, float]]] = {k: [] for k in rows}
    for _ in range(args.repeat):  # interleave so drift hits both alike
        for name, (py, code) in rows.items():
            results[name].append(run(py, code.format(repo=str(REPO), root=root, version=VERSION)))
    print(f"\n{'reader':<12} {'load s (median)':>16} {'all runs':>22} {'peak RSS MiB':>13}")
    med = {}
    for name, res in results.items():
        med[name] = statistics.median(r[0] for r in res)
        runs = ", ".join(f"{r[0]:.1f}" for r in res)
        print(f"{name:<12} {med[name]:>16.2f} {runs:>22} {max(r[1] for r in res):>13.0f}")
    if "devkit" in med:
        print(f"\nrenderworld / devkit time ratio: {med['renderworld'] / med['devkit']:.2f} "
              f"(goal <= 0.5)")  # fmt: skip


if __name__ == "__main__":
    main()
