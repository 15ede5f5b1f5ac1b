"""Data-parallel training with torchrun (gloo, CPU): equivalence with one process, files, resume, failures.

Every torchrun here starts ``python -m torch.distributed.run --standalone`` (a free port) with 2 CPU
processes of one thread each, on a tiny model and 64² patches.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from helpers.tilefolder import write_tile_folder

from aerialmtl.formats.checkpoint import load_checkpoint
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train

ROOT = Path(__file__).resolve().parents[1]
TINY = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2}
STEPS = 10
#: Tolerance of "2 processes × 4 follow 1 process × 8" on the logged loss of each of the 10 steps. Both see
#: the same patches, augmentations and (SyncBatchNorm) statistics; only the order of float additions differs
#: (per-process sums, the gradient all-reduce), and Adam (β1 = 0.5) amplifies such rounding: one process with
#: 2 torch threads instead of 1 already moves these losses by up to 3e-4 (relative) at step 10, and the
#: 2-process run stays within 1e-3. Without SyncBatchNorm (statistics of 4 patches) they drift by up to 1e-2.
#: Weights are not compared: the same rounding moves near-zero-gradient parameters (BatchNorm biases) by
#: whole Adam steps, for thread counts as much as for processes.
LOSS_RTOL = 2e-3


def cfg_dict(batch_size: int, sync_bn: bool) -> dict:
    # dropout 0: each process draws its own dropout masks, which cannot match one process's masks
    return {"model": {**TINY, "dropout": 0.0, "sync_bn": sync_bn},
            "data": {"batch_size": batch_size, "num_workers": 0, "jitter": True},
            "optim": {"lr": 2e-3}, "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu"}


def torchrun(nproc: int, args: list[str], record: Path | None = None, watched: Path | None = None,
             wait: bool = True) -> subprocess.CompletedProcess | subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "OMP_NUM_THREADS": "1"}
    target = ["-m", "aerialmtl"] if record is None else [str(ROOT / "tests" / "torchrun_audit.py"), str(watched),
                                                          str(record)]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
           *target, *args]
    if not wait:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


def train_rows(log: Path) -> list[dict[str, str]]:
    with log.open() as fh:
        return [r for r in csv.DictReader(fh) if r["kind"] == "train"]


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 16 train patches: a global batch of 8 → 2 steps per epoch. No invalid pixels, so every process's
    # masked mean covers as many pixels and their average is exactly the one-process mean.
    return write_tile_folder(tmp_path_factory.mktemp("ddp") / "tiles", size=64, counts={"train": 16, "val": 4},
                             invalid_corner=False)


@pytest.fixture(scope="module")
def two_rank_run(tiles: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """2 processes × batch 4 with SyncBatchNorm, 10 steps, run through the audit wrapper."""
    root = tmp_path_factory.mktemp("two")
    cfg = root / "c.yaml"
    cfg.write_text(yaml.safe_dump(cfg_dict(4, sync_bn=True)))
    run = root / "run"
    res = torchrun(2, ["train", "--config", str(cfg), "--data", str(tiles), "--out", str(run), "--max-steps",
                       str(STEPS), "--quiet"], record=root / "writes", watched=run)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return {"run": run, "writes": root / "writes"}


@pytest.mark.slow  # ~20 s: the module's 2-process torchrun (fixture) plus one process training 10 steps
def test_two_processes_follow_one_process_with_twice_the_batch(two_rank_run: dict[str, Path], tiles: Path,
                                                              tmp_path: Path) -> None:
    one = train(TrainConfig.from_dict(cfg_dict(8, sync_bn=False)), tiles, tmp_path / "one", max_steps=STEPS,
                progress=False)
    a = [float(r["loss"]) for r in train_rows(one.log_path)]
    b = [float(r["loss"]) for r in train_rows(two_rank_run["run"] / "log.csv")]
    assert len(a) == len(b) == STEPS
    assert b == pytest.approx(a, rel=LOSS_RTOL)
    assert a[-1] < 0.7 * a[0]  # it learned, so the comparison is not between two constants
    payload, _ = load_checkpoint(two_rank_run["run"] / "last.pt")
    ts = payload["train_state"]
    assert (ts["step"], ts["epoch"], ts["position"], ts["world_size"], ts["global_batch"]) == (STEPS, 5, 0, 2, 8)
    assert len(ts["rng_ranks"]) == 2


def test_only_rank_zero_writes_files(two_rank_run: dict[str, Path]) -> None:
    rank0 = (two_rank_run["writes"] / "writes-rank0.txt").read_text().splitlines()
    rank1 = (two_rank_run["writes"] / "writes-rank1.txt").read_text().splitlines()
    assert rank1 == []
    assert any("log.csv" in e for e in rank0) and any("config.yaml" in e for e in rank0)
    assert any(e.startswith("os.rename") or e.startswith("os.replace") for e in rank0)  # checkpoints moved in place
    run = two_rank_run["run"]
    assert sorted(p.name for p in run.iterdir()) == ["best.pt", "config.yaml", "last.pt", "log.csv"]
    steps = [int(r["step"]) for r in train_rows(run / "log.csv")]
    assert steps == list(range(1, STEPS + 1))  # one row per step: not written twice


def test_two_process_run_resumed_by_one_process(two_rank_run: dict[str, Path], tiles: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    for f in ("last.pt", "config.yaml", "log.csv"):
        (run / f).write_bytes((two_rank_run["run"] / f).read_bytes())
    cfg = TrainConfig.from_dict(cfg_dict(4, sync_bn=True))
    res = train(cfg, tiles, run, max_steps=STEPS + 2, resume=True, progress=False)
    assert res.step == STEPS + 2
    steps = [int(r["step"]) for r in train_rows(res.log_path)]
    assert steps == list(range(1, STEPS + 3))
    ts = load_checkpoint(res.last_checkpoint)[0]["train_state"]
    # the 2-process run ended an epoch; one process with batch 4 used positions 0-3 and 4-7 of the next
    assert (ts["epoch"], ts["position"], ts["world_size"], ts["global_batch"]) == (5, 8, 1, 4)


def _child_with_rank(parent: int, rank: int) -> int | None:
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) != parent:
                continue
            if f"RANK={rank}".encode() in (d / "environ").read_bytes().split(b"\0"):
                return int(d.name)
        except (OSError, ValueError, IndexError):
            continue
    return None


@pytest.mark.slow  # a long torchrun is started, watched and killed
@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the rank's process through /proc")
def test_a_dying_process_stops_the_others_and_the_checkpoint_stays_whole(tiles: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(cfg_dict(4, sync_bn=True)))
    run = tmp_path / "run"
    proc = torchrun(2, ["train", "--config", str(cfg), "--data", str(tiles), "--out", str(run), "--max-steps",
                        "100000", "--quiet"], wait=False)
    assert isinstance(proc, subprocess.Popen)
    try:
        deadline = time.time() + 300
        while not (run / "last.pt").exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert (run / "last.pt").exists(), "the run never wrote a checkpoint"
        victim = _child_with_rank(proc.pid, 1)  # torchrun's workers are its children
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    assert "[rank 0] another process of this multi-process run failed" in out
    assert "continue with --resume" in out
    payload, _ = load_checkpoint(run / "last.pt")  # whole: loads and holds a training state
    assert payload["train_state"]["step"] >= 1
    assert not list(run.glob(".*tmp*"))  # no temporary checkpoint left behind
