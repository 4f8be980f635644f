"""bench/e2e.py's training on another machine (a GPU host) from captures made here.

The capture (pycolmap) and the evaluation (the ground truth) stay on the machine that has them. A GPU host
gets, per garment, the video and its finished capture without the frames (200 PNGs of 720x1280 are
hundreds of MB; the same video and code extract the same frames again, checked against the frames the
poses stage saw), trains a job per garment and weight with the default options on its device, all at
once, and hands back one archive per job: the stage records and the run with its last checkpoint. Here,
each archive becomes the job folder that ``bench/e2e.py --preset P --tag T`` finds trained; it meshes,
exports and evaluates it like any other run (meshing culls with open3d, which that host need not have).

    .venv/bin/python bench/remote.py pack --dest ship                 # here: captures and videos
    python3 bench/remote.py run ship --weights neudf                  # there: starts the jobs, returns
    python3 bench/remote.py wait ship --out OUT                       # there: an archive per job that ends
    .venv/bin/python bench/remote.py unpack OUT/*.tar.gz --tag cuda   # here: the job folders
    .venv/bin/python bench/e2e.py --preset gpu --tag cuda --out bench/results/e2e_neudf_cuda.json

There it needs torch, numpy, scipy, Pillow, OpenCV and scikit-image (a CUDA image tends to have them) and
PyAV, pydantic and trimesh, nothing else of the project's (checked in a virtual environment with only these).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from worker.pipeline import STAGE_NAMES  # noqa: E402

WORK = Path("/tmp/neudf-bench-e2e")
CAPTURE_STAGES = ("frames", "poses", "scene")
WEIGHTS = ("neudf", "neus_sdf", "neus_abs")
# What the capture leaves that training and meshing do not read, or that extraction writes again; of
# COLMAP's files only poses.json (it marks the poses stage done) and frames_all.json (the frames it saw).
LEFT_BEHIND = ("image", "export", "run", "mesh", "database.db", "sparse", "undistorted")


def pack(work: Path, names: list[str] | None, dest: Path) -> None:
    """Copy each finished capture (``<name>_neudf`` in work/jobs) without its frames, and its video, into dest."""
    jobs = sorted(p for p in (work / "jobs").glob("*_neudf") if (p / "stages" / "scene.json").is_file())
    for job in jobs:
        name = job.name.removesuffix("_neudf")
        if names and name not in names:
            continue
        shutil.copytree(job, dest / "jobs" / name, ignore=shutil.ignore_patterns(*LEFT_BEHIND), dirs_exist_ok=True)
        (dest / "videos").mkdir(parents=True, exist_ok=True)
        shutil.copy2(work / "videos" / f"{name}.mp4", dest / "videos" / f"{name}.mp4")
        print(f"packed {name}")


def restore_frames(job: Path, video: Path) -> None:
    """DATA/image again from the video: the frames stage's extraction, checked against the frames the poses
    stage saw, then renumbered as the scene stage kept them. Frames COLMAP had to undistort cannot be made
    again without it."""
    from worker.capture.frames import extract_frames

    data = job / "data"
    if (data / "image").is_dir():
        return
    if json.loads((data / "colmap" / "poses.json").read_text()).get("undistorted"):
        raise SystemExit(f"{job.name}: its frames were undistorted by COLMAP; carry data/image instead")
    with tempfile.TemporaryDirectory(dir=job) as tmp:
        options = json.loads((job / "stages" / "frames.json").read_text()).get("options", {})
        kwargs = {k: v for k, v in (("n_frames", options.get("frames")), ("max_size", options.get("max_size")))
                  if v is not None}
        extract_frames(video, tmp, **kwargs)
        extracted = {e["frame_index"]: e["file"] for e in json.loads((Path(tmp) / "frames.json").read_text())}
        seen = [e["frame_index"] for e in json.loads((data / "colmap" / "frames_all.json").read_text())]
        if sorted(extracted) != seen:
            raise SystemExit(f"{job.name}: the video gives other frames than its capture used")
        staging = Path(tmp) / "kept"
        staging.mkdir()
        for entry in json.loads((data / "frames.json").read_text()):
            shutil.move(str(Path(tmp) / "image" / extracted[entry["frame_index"]]), str(staging / entry["file"]))
        shutil.move(str(staging), str(data / "image"))


def run_one(job: Path, video: Path, weight: str, until: str, device: str, minutes: float | None) -> None:
    """The job's stages after the capture, up to ``until``, with the default options but ``weight`` (and
    ``minutes`` where given)."""
    from neudf_core.progress import Cancelled
    from worker.pipeline import JobOptions, run_pipeline

    restore_frames(job, video)
    last, shown = STAGE_NAMES.index(until), [0.0]

    def report(fraction: float, message: str = "", **info: Any) -> None:
        if info.get("event") == "start" and STAGE_NAMES.index(info["stage"]) > last:
            raise Cancelled(f"stopped after {until}")
        if info.get("event") in ("start", "done", "skipped") or time.time() - shown[0] > 30:
            print(f"{time.strftime('%H:%M:%S')} {fraction * 100:5.1f}% {message}", flush=True)
            shown[0] = time.time()

    try:
        run_pipeline(video, job, JobOptions(weight=weight, minutes=minutes), report, device=device)
    except Cancelled:
        pass


def run_list(ship: Path) -> list[Path]:
    folder = ship / "runs"
    return sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []


def run(ship: Path, weights: list[str], until: str, device: str, minutes: float | None) -> None:
    """One process per garment and weight, all at once, each in ship/runs/<garment>_<weight> (a copy of the
    capture); each writes remote.log there, and remote.rc when it ends. Returns once they are started."""
    for capture in sorted(p for p in (ship / "jobs").iterdir() if p.is_dir()):
        for weight in weights:
            job = ship / "runs" / f"{capture.name}_{weight}"
            if job.exists():  # started by an earlier call (captures may arrive in parts)
                continue
            shutil.copytree(capture, job)
            video = ship / "videos" / f"{capture.name}.mp4"
            cmd = (f"{sys.executable} {Path(__file__).resolve()} one {job} {video} --weight {weight} "
                   f"--until {until} --device {device}{f' --minutes {minutes}' if minutes else ''} "
                   f"> {job / 'remote.log'} 2>&1; echo $? > {job / 'remote.rc'}")
            # a session of its own: it outlives this command on hosts that end a command's process group
            subprocess.Popen(["bash", "-c", cmd], start_new_session=True)
            print(f"started {job.name}", flush=True)


def wait(ship: Path, until: str, out: Path, timeout_s: float | None) -> None:
    """Write each job's archive into ``out`` as soon as it ends, until all have ended (or ``timeout_s``)."""
    t0, done = time.time(), set()
    out.mkdir(parents=True, exist_ok=True)
    while True:
        jobs = run_list(ship)
        for job in jobs:
            if job.name in done or not (job / "remote.rc").is_file():
                continue
            done.add(job.name)
            log = (job / "remote.log").read_text()
            print(f"== {job.name}: exit {(job / 'remote.rc').read_text().strip()}\n{log[-1500:]}", flush=True)
            if (job / "stages" / f"{until}.json").is_file():
                archive(job, until, out / f"{job.name}.tar.gz")
        if len(done) == len(jobs) or (timeout_s is not None and time.time() - t0 > timeout_s):
            break
        time.sleep(5)
    for job in jobs:
        if job.name not in done:
            print(f"== {job.name}: still running\n{(job / 'remote.log').read_text()[-600:]}", flush=True)


def archive(job: Path, until: str, path: Path) -> None:
    """The stage records, run folder and mesh of a finished job (what export and evaluation read)."""
    with tarfile.open(path, "w:gz") as tar:
        for stage in STAGE_NAMES[len(CAPTURE_STAGES):STAGE_NAMES.index(until) + 1]:
            tar.add(job / "stages" / f"{stage}.json", f"stages/{stage}.json")
        latest = sorted((job / "run" / "checkpoints").glob("ckpt_*.pt"))[-1:]  # the one meshing reads
        tar.add(job / "run", "run", filter=lambda m: None if "/checkpoints/" in m.name and
                not any(m.name.endswith(p.name) for p in latest) else m)
        if (job / "mesh").is_dir():
            tar.add(job / "mesh", "mesh")
        tar.add(job / "remote.log", "remote.log")


def unpack(archives: list[Path], work: Path, tag: str) -> None:
    """Each archive on top of a copy of its garment's capture, as the job folder that
    ``bench/e2e.py --weight W --preset P --tag TAG`` finishes: ``<garment>_<W>_<P>_<TAG>`` (P, the preset the
    run trained with)."""
    for path in archives:
        name = path.name.removesuffix(".tar.gz")  # <garment>_<weight>
        weight = next(w for w in WEIGHTS if name.endswith(f"_{w}"))
        garment = name.removesuffix(f"_{weight}")
        with tarfile.open(path) as tar:
            preset = json.load(tar.extractfile("stages/train.json"))["options"]["preset"]
            source, job = work / "jobs" / f"{garment}_neudf", work / "jobs" / f"{name}_{preset}_{tag}"
            shutil.rmtree(job, ignore_errors=True)
            shutil.copytree(source / "data", job / "data")
            (job / "stages").mkdir(parents=True)
            for stage in CAPTURE_STAGES:
                shutil.copy2(source / "stages" / f"{stage}.json", job / "stages" / f"{stage}.json")
            tar.extractall(job, filter="data")
        print(f"unpacked {job}: bench/e2e.py --meshes {garment} --weight {weight} --preset {preset} --tag {tag}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="Here: copy finished captures and their videos into --dest.")
    p.add_argument("--work", type=Path, default=WORK)
    p.add_argument("--meshes", nargs="*")
    p.add_argument("--dest", type=Path, required=True)
    p = sub.add_parser("run", help="There: start a job per garment and weight, and return.")
    p.add_argument("ship", type=Path)
    p.add_argument("--weights", nargs="+", default=["neudf"], choices=WEIGHTS)
    p.add_argument("--until", default="train", choices=STAGE_NAMES[len(CAPTURE_STAGES):])
    p.add_argument("--device", default="auto")
    p.add_argument("--minutes", type=float, help="Training budget (default: the job default).")
    p = sub.add_parser("wait", help="There: wait for the jobs, then write an archive per finished one to --out.")
    p.add_argument("ship", type=Path)
    p.add_argument("--until", default="train", choices=STAGE_NAMES[len(CAPTURE_STAGES):])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--timeout", type=float, help="Seconds to wait at most.")
    p = sub.add_parser("one", help="One job (what run starts for each).")
    p.add_argument("job", type=Path)
    p.add_argument("video", type=Path)
    p.add_argument("--weight", default="neudf", choices=WEIGHTS)
    p.add_argument("--until", default="train")
    p.add_argument("--device", default="auto")
    p.add_argument("--minutes", type=float)
    p = sub.add_parser("unpack", help="Here: archives into job folders for bench/e2e.py --preset P --tag T.")
    p.add_argument("archives", type=Path, nargs="+")
    p.add_argument("--work", type=Path, default=WORK)
    p.add_argument("--tag", default="cuda", help="Names the runs (the machine they trained on).")
    args = parser.parse_args()

    if args.command == "pack":
        pack(args.work, args.meshes, args.dest)
    elif args.command == "run":
        from neudf_core.device import resolve_device

        run(args.ship, args.weights, args.until, resolve_device(args.device), args.minutes)
    elif args.command == "wait":
        wait(args.ship, args.until, args.out, args.timeout)
    elif args.command == "one":
        from neudf_core.device import resolve_device

        run_one(args.job, args.video, args.weight, args.until, resolve_device(args.device), args.minutes)
    else:
        unpack(args.archives, args.work, args.tag)


if __name__ == "__main__":
    main()
