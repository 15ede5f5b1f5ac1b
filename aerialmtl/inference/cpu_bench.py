"""``aerialmtl bench``: how fast each engine × precision predicts on the CPU at hand, so any user can send numbers.

For each model (the paper's full D3-Net and the small-area one, untrained, heads drawn so that heights are a
few metres and classes confident, as a trained model's are) and each engine × precision:

* **model alone**: Mpx/s of the engine on ``window``² windows (one batch per stream kept in flight, as
  ``predict`` runs it), and how far its maps are from torch fp32's on the same window (height MAE in metres,
  share of pixels whose class agrees; :data:`~aerialmtl.inference.engine_choice.TOLERANCES`);
* **end to end**: ``aerialmtl predict`` in a subprocess on a synthetic ``size``² orthophoto, T = 1, the whole
  process timed (start-up included) and the stage timings of its ``prediction.json``; OpenVINO runs twice and
  the faster run counts (the first fills its engine cache, as a user's first run does once).

``int8`` (OpenVINO post-training quantisation with NNCF, calibrated on synthetic windows) is measured for the
model alone where NNCF is installed; ``predict`` has no int8 path, so it is never chosen.

Every row carries the load average before and after it (the numbers of a shared CPU are not a quiet CPU's), and
the report the CPU's name, family/model and kind (:func:`~aerialmtl.inference.engine_choice.cpu_kind`), plus the
ISA cap when one emulates a smaller CPU (``ONEDNN_MAX_CPU_ISA``).
:func:`best_entry` turns a report into the table entry of its kind, :func:`write_table` merges it into a table.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import nn

from aerialmtl import runtime
from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.cpuinfo import cpu_fields, cpu_flags
from aerialmtl.formats.checkpoint import ModelMeta, save_checkpoint
from aerialmtl.inference.engine_choice import CPU_KINDS, TOLERANCES, KindEntry, cpu_kind, layout_of
from aerialmtl.inference.engines import ENGINES, FALLBACK
from aerialmtl.inference.runner import ModelRunner
from aerialmtl.inference.settings import PredictSettings, ResolvedSettings
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net, TaskDecoder, inference_model
from aerialmtl.models.mc_dropout import McStatistics

#: The models of the bench: ModelConfig fields over its defaults (the paper's DenseNet-121 D3-Net).
MODELS: dict[str, dict[str, Any]] = {
    "full": {},
    "small": {"growth_rate": 12, "block_config": (2, 4, 6, 4), "num_init_features": 24, "bn_size": 2},
}
#: The case every other is compared with (speed and accuracy): the torch engine at fp32.
REFERENCE = (FALLBACK, "fp32")
#: Engine × precision cases, in the order they run: the reference engine's first (its fp32 first), then those of
#: every other engine of the registry, at the precisions each declares (``EngineSpec.precisions``).
CASES: tuple[tuple[str, str], ...] = tuple(
    (name, precision) for name in sorted(ENGINES, key=lambda name: name != FALLBACK)
    for precision in ENGINES[name].precisions)
NUM_CLASSES = 20
#: Standard deviation of the drawn head weights per task (an untrained head's near-zero outputs would make every
#: class a tie and every height 0 m, and the accuracy columns meaningless).
HEAD_STD = {"height": 0.3, "classes": 1.0}


@dataclass(frozen=True)
class BenchSettings:
    """What ``aerialmtl bench`` measures.

    Attributes:
        models: names of :data:`MODELS`. cases: ``(engine, precision)`` pairs of :data:`CASES`.
        window: side of the model-alone windows (pixels, multiple of 32); windows: how many are timed per case.
        size: side of the end-to-end synthetic orthophoto (pixels); ``0`` skips the end-to-end runs.
        threads: inference threads (``auto`` as ``predict``).
        workdir: where the checkpoints, rasters, OpenVINO cache and outputs go (default: a temporary folder).
    """

    models: tuple[str, ...] = ("full", "small")
    cases: tuple[tuple[str, str], ...] = CASES
    window: int = 512
    windows: int = 2
    size: int = 1024
    threads: int | str = "auto"
    workdir: Path | None = None


@dataclass
class BenchRow:
    """One measurement.

    ``stage``: ``model`` (alone) or ``end-to-end``; ``mpx_s``: output megapixels per second; ``seconds``: per
    window (model) or per process (end to end); accuracy against torch fp32 (model alone); ``load``: load average
    (1 min) before → after; ``note``: why a case was skipped, or the stage timings.
    """

    model: str
    engine: str
    precision: str
    stage: str
    mpx_s: float | None = None
    seconds: float | None = None
    height_mae_m: float | None = None
    height_rel_mae: float | None = None
    class_agreement: float | None = None
    load: tuple[float, float] = (0.0, 0.0)
    note: str = ""


@dataclass
class BenchReport:
    """The CPU, the settings and the rows of a bench run."""

    cpu: dict[str, Any]
    settings: dict[str, Any]
    rows: list[BenchRow] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``aerialmtl bench --json``)."""
        return {"cpu": self.cpu, "settings": self.settings, "rows": [asdict(r) for r in self.rows]}


def cpu_info() -> dict[str, Any]:
    """Name, family/model, kind, the flags that matter for the engines, cores and the ISA cap of this CPU."""
    info: dict[str, Any] = {"name": platform.processor() or platform.machine(), "kind": cpu_kind(),
                            "cores": os.cpu_count(), "isa_cap": os.environ.get("ONEDNN_MAX_CPU_ISA"),
                            "machine": platform.machine()}
    fields = cpu_fields()
    if "model name" in fields:
        info["name"] = fields["model name"]
    for key in ("cpu family", "model"):
        if key in fields:
            info[key.replace(" ", "_")] = fields[key]
    if "flags" in fields:
        info["flags"] = sorted(cpu_flags() & {"avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16",
                                              "amx_bf16", "amx_int8"})
    return info


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def bench_model(name: str, seed: int = 0) -> tuple[D3Net, ModelMeta]:
    """The bench's model ``name`` (:data:`MODELS`) and its metadata: untrained, heads drawn (normal, std 0.3)."""
    torch.manual_seed(seed)
    cfg = ModelConfig(num_classes=NUM_CLASSES, **MODELS[name])
    model = D3Net(cfg).eval()
    with torch.no_grad():  # heights of a few metres, class logits a few units apart (a trained model's margins)
        for task, head in model.heads.items():
            assert isinstance(head, TaskDecoder)  # nn.ModuleDict holds plain Modules for mypy
            torch.nn.init.normal_(head.head.weight, std=HEAD_STD[task])
    scheme = ClassScheme("bench", tuple(ClassDef(i + 1, f"c{i}", (i * 12 % 256, 100, 200))
                                        for i in range(NUM_CLASSES)))
    return model, ModelMeta(cfg, scheme, (1, 2, 3), (110.0, 110.0, 100.0), (45.0, 45.0, 45.0), 0.5)


def synthetic_window(size: int, seed: int = 0) -> np.ndarray:
    """A (3, size, size) uint8 orthophoto-like window: smooth blobs plus noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    base = 120 + 60 * np.sin(xx / 37.0 + seed) * np.cos(yy / 23.0)
    bands = np.stack([base + rng.normal(0, 10, (size, size)) + 10 * i for i in range(3)])
    return np.asarray(np.clip(bands, 0, 255), dtype=np.uint8)


def _maps(stats: Any) -> tuple[np.ndarray, np.ndarray]:
    return stats.height_mean.float().numpy()[0], stats.probs.float().numpy()[0].argmax(-1)


def _compare(maps: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> tuple[float, float, float]:
    """Height MAE (m), height MAE relative to the reference's mean |height|, class agreement of ``maps``."""
    mae = float(np.abs(maps[0] - ref[0]).mean())
    return mae, mae / max(float(np.abs(ref[0]).mean()), 1e-6), float((maps[1] == ref[1]).mean())


def _model_alone(model: nn.Module, meta: ModelMeta, engine: str, precision: str, settings: BenchSettings,
                 x: torch.Tensor) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """Seconds per window of ``engine``/``precision`` (``bf16`` or ``fp32``), and its maps of the first window."""
    threads = runtime.resolve_threads(settings.threads)
    resolved = runtime.resolve_precision(precision, torch.device("cpu"))  # bf16 or fp32 as they are
    asked = PredictSettings(engine=engine, precision=resolved, mc=1, threads=settings.threads)
    runner = ModelRunner(model, meta, asked, ResolvedSettings(torch.device("cpu"), engine, resolved, threads, 1))
    maps = _maps(runner(x, [0]))  # conversion or compilation, warm-up
    pending: deque[Any] = deque()
    t0 = time.perf_counter()
    for k in range(settings.windows):
        pending.append(runner.submit(x, [k]))
        while len(pending) > runner.in_flight:
            pending.popleft().result()
    while pending:
        pending.popleft().result()
    return (time.perf_counter() - t0) / settings.windows, maps


def _int8_alone(model: nn.Module, meta: ModelMeta, settings: BenchSettings,
                x: torch.Tensor) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """The model quantised to int8 by NNCF (calibrated on 8 synthetic windows), on OpenVINO: as :func:`_model_alone`.

    Raises:
        ImportError: NNCF is not installed.
    """
    import nncf  # noqa: F401 - the ImportError says it is missing

    ov = runtime.import_openvino()
    net = inference_model(model, torch.device("cpu"))

    class Graph(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, inp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            out = self.net(inp)
            return out["height"], out["classes"]

    with torch.no_grad():
        ov_model = ov.convert_model(Graph().eval(), example_input=x)
    mean = np.array(meta.mean, np.float32)[:, None, None]
    std = np.array(meta.std, np.float32)[:, None, None]
    side = min(256, x.shape[-1])
    calib = [((synthetic_window(side, seed=s).astype(np.float32) - mean) / std)[None] for s in range(8)]
    quantised = nncf.quantize(ov_model, nncf.Dataset(calib), subset_size=len(calib))
    threads = runtime.resolve_threads(settings.threads)
    compiled = runtime.openvino_core().compile_model(quantised, "CPU", {"INFERENCE_NUM_THREADS": threads.threads,
                                                                       "NUM_STREAMS": threads.streams,
                                                                       "ENABLE_CPU_PINNING": False})
    inp = x.contiguous().numpy()

    def run() -> tuple[np.ndarray, np.ndarray]:
        res = compiled(inp)
        return np.asarray(res[0]), np.asarray(res[1])

    height, logits = run()
    stats = McStatistics(height_mean=torch.from_numpy(height[:, 0]),
                         probs=torch.from_numpy(np.moveaxis(logits, 1, -1)))
    queue = ov.AsyncInferQueue(compiled, threads.streams)
    t0 = time.perf_counter()
    for _ in range(settings.windows):
        queue.start_async({0: inp})
    queue.wait_all()
    return (time.perf_counter() - t0) / settings.windows, _maps(stats)


def _synthetic_raster(path: Path, size: int) -> Path:
    """A 3-band uint8 GeoTIFF of ``size``² pixels (0.5 m, UTM 31N) written block by block."""
    import rasterio
    from affine import Affine
    from rasterio.windows import Window

    block = 512
    profile = dict(driver="GTiff", width=size, height=size, count=3, dtype="uint8", crs="EPSG:32631",
                   transform=Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0), tiled=True, blockxsize=block,
                   blockysize=block)
    with rasterio.open(path, "w", **profile) as dst:
        for r in range(0, size, block):
            for c in range(0, size, block):
                h, w = min(block, size - r), min(block, size - c)
                dst.write(synthetic_window(max(h, w), seed=r * 7 + c)[:, :h, :w], window=Window(c, r, w, h))
    return path


def end_to_end(checkpoint: Path, raster: Path, out: Path, engine: str, precision: str, mc: int = 1,
               threads: int | str = "auto", env: dict[str, str] | None = None) -> tuple[float, dict[str, Any]]:
    """Wall seconds of ``aerialmtl predict`` in a subprocess (start-up included) and its ``prediction.json``.

    Raises:
        RuntimeError: the command failed (with the end of its stderr).
    """
    cmd = [sys.executable, "-m", "aerialmtl", "predict", str(raster), "--model", str(checkpoint), "--out", str(out),
           "--mc", str(mc), "--engine", engine, "--precision", precision, "--threads", str(threads), "--quiet",
           "--overwrite"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-1500:]}")
    return wall, json.loads((out / "prediction.json").read_text())


def run_bench(settings: BenchSettings, on_row: Callable[[BenchRow], None] | None = None) -> BenchReport:
    """Measure every model × case of ``settings`` (see the module docstring); ``on_row`` sees each row as it comes."""
    report = BenchReport(cpu_info(), {k: (str(v) if isinstance(v, Path) else v) for k, v in
                                      asdict(settings).items()})

    def add(row: BenchRow) -> None:
        report.rows.append(row)
        if on_row is not None:
            on_row(row)

    native_bf16 = runtime.native_bf16(torch.device("cpu"))
    with tempfile.TemporaryDirectory(prefix="aerialmtl-bench-") as tmp:
        work = settings.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        os.environ.setdefault("AERIALMTL_OPENVINO_CACHE", str(work / "openvino-cache"))
        raster = _synthetic_raster(work / f"ortho_{settings.size}.tif", settings.size) if settings.size else None
        window = torch.from_numpy(synthetic_window(settings.window)).float()
        for name in settings.models:
            model, meta = bench_model(name)
            mean = torch.tensor(meta.mean)[:, None, None]
            std = torch.tensor(meta.std)[:, None, None]
            x = ((window - mean) / std)[None].contiguous(memory_format=torch.channels_last)
            ref: tuple[np.ndarray, np.ndarray] | None = None
            for engine, precision in settings.cases:
                row = BenchRow(name, engine, precision, "model")
                before = _load()
                if precision == "bf16" and not native_bf16:
                    row.note = "skipped: this CPU has no native bf16 (it would be emulated, many times slower)"
                else:
                    try:
                        if precision == "int8":
                            seconds, maps = _int8_alone(model, meta, settings, x)
                        else:
                            seconds, maps = _model_alone(model, meta, engine, precision, settings, x)
                    except ImportError as exc:
                        row.note = f"skipped: {exc.name or exc} is not installed"
                    else:
                        ref = maps if ref is None else ref
                        row.seconds = round(seconds, 3)
                        row.mpx_s = round(settings.window ** 2 / 1e6 / seconds, 4)
                        row.height_mae_m, row.height_rel_mae, row.class_agreement = (
                            round(v, 5) for v in _compare(maps, ref))
                row.load = (before, _load())
                add(row)
            if raster is None:
                continue
            ckpt = work / f"{name}.pt"
            save_checkpoint(ckpt, model, meta)
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
            for engine, precision in settings.cases:
                row = BenchRow(name, engine, precision, "end-to-end")
                before = _load()
                if precision == "int8":
                    row.note = "skipped: predict has no int8 path"
                elif precision == "bf16" and not native_bf16:
                    row.note = "skipped: this CPU has no native bf16"
                else:
                    runs = [end_to_end(ckpt, raster, work / f"out_{name}", engine, precision,
                                       threads=settings.threads, env=env)
                            for _ in range(2 if ENGINES[engine].compile_mpx else 1)]  # the first fills its cache
                    wall, info = min(runs, key=lambda run: run[0])
                    row.seconds = round(wall, 2)
                    row.mpx_s = round(settings.size ** 2 / 1e6 / wall, 4)
                    row.note = "stages " + ", ".join(f"{k} {v:.2f}" for k, v in info.get("timings_s", {}).items())
                row.load = (before, _load())
                add(row)
    return report


def within_tolerance(row: BenchRow) -> bool:
    """Whether ``row``'s maps stay within :data:`~aerialmtl.inference.engine_choice.TOLERANCES` of its precision."""
    bound = TOLERANCES.get(row.precision)
    if bound is None or row.class_agreement is None or row.height_mae_m is None:
        return False
    rel = row.height_rel_mae if row.height_rel_mae is not None else float("inf")
    return (row.height_mae_m <= bound.get("height_mae_m", float("inf"))
            and rel <= bound.get("height_rel_mae", float("inf"))
            and row.class_agreement >= bound["class_agreement"])


def best_entry(report: BenchReport, model: str = "full") -> KindEntry:
    """The table entry of the report's CPU kind: the fastest engine × precision of ``model`` within the tolerances.

    Fastest by model-alone speed among those whose maps stay within the tolerances (:func:`within_tolerance`;
    int8 is never chosen: ``predict`` has no int8 path). The model-alone speed decides, not the end-to-end one:
    it is measured back to back in one process, while one end-to-end run per case on a small raster is mostly
    start-up and, on a shared CPU, the load of the moment. ``speedup`` is the end-to-end ratio over torch fp32
    where both were measured (else the model-alone ratio), and ``measured`` says which.

    Raises:
        ValueError: the report has no measured row of ``model`` within the tolerances, or its best is no
            engine/precision of the table (a case outside :data:`CASES`).
    """
    alone = {(r.engine, r.precision): r for r in report.rows if r.model == model and r.stage == "model"}
    pool = {key: r for key, r in alone.items() if r.mpx_s is not None and within_tolerance(r) and key[1] != "int8"}
    if not pool:
        raise ValueError(f"no engine × precision of the {model} model was measured within the tolerances")
    (engine, precision), best = max(pool.items(), key=lambda kv: kv[1].mpx_s or 0.0)
    match precision:  # the table's choices (``bench``'s cases are these and int8, left out above)
        case "fp32" | "bf16" as chosen_precision if engine in ENGINES:
            pass
        case _:
            raise ValueError(f"{engine}/{precision} is no choice of the engine table; measure "
                             f"{' or '.join(ENGINES)} in fp32 or bf16")
    e2e = {(r.engine, r.precision): r for r in report.rows if r.model == model and r.stage == "end-to-end"
           and r.mpx_s is not None}
    pair = (e2e.get((engine, precision)), e2e.get(REFERENCE))
    if pair[0] is None or pair[1] is None:
        pair, ratio_of = (best, alone.get(REFERENCE)), "model alone"
    else:
        ratio_of = "end to end"
    speedup = round(pair[0].mpx_s / pair[1].mpx_s, 2) if pair[0] and pair[1] and pair[0].mpx_s and pair[1].mpx_s \
        else None
    cpu = report.cpu
    loads = [v for r in report.rows for v in r.load]
    how = "emulated" if cpu.get("isa_cap") else "reached"
    measured = (f"{how}: {cpu.get('name')} family {cpu.get('cpu_family')} model {cpu.get('model')}"
                f"{', ONEDNN_MAX_CPU_ISA=' + cpu['isa_cap'] if cpu.get('isa_cap') else ''}, {cpu.get('cores')} cores, "
                f"load {min(loads, default=0):.1f}-{max(loads, default=0):.1f}, chosen on the model alone, speedup "
                f"{ratio_of}, {datetime.now(timezone.utc).date()}")
    return KindEntry(
        engine=engine, precision=chosen_precision, layout=layout_of(ENGINES[engine]),
        speedup=speedup, measured=measured,
        model_alone_mpx_s={f"{e}/{p}": r.mpx_s for (e, p), r in alone.items() if r.mpx_s is not None},
        accuracy={f"{e}/{p}": {"height_mae_m": float(r.height_mae_m), "height_rel_mae": float(r.height_rel_mae or 0),
                               "class_agreement": float(r.class_agreement or 0),
                               "within_tolerance": float(within_tolerance(r))}
                  for (e, p), r in alone.items() if r.height_mae_m is not None},
        notes="int8 is measured for the model alone only; predict has no int8 path"
        if any(p == "int8" for _, p in alone) else "")


def write_table(path: Path, kind: str, entry: KindEntry) -> None:
    """Set ``kind``'s entry of the table at ``path`` (created if absent; the other kinds are kept)."""
    if kind not in CPU_KINDS:
        raise ValueError(f"unknown CPU kind {kind!r}")
    data: dict[str, Any] = yaml.safe_load(path.read_text(encoding="utf-8")) if path.is_file() else {}
    data = data or {}
    kinds = data.setdefault("kinds", {})
    kinds[kind] = {k: v for k, v in asdict(entry).items() if v not in ("", None, {})}
    data["tolerances"] = {k: dict(v) for k, v in TOLERANCES.items()}
    head = ("# What `--engine auto` runs per CPU kind (aerialmtl.inference.engine_choice), written by\n"
            "# `aerialmtl bench --write-table` on a CPU of each kind; a kind absent here keeps the rule before the\n"
            "# table (OpenVINO where installed, bf16 where native). Speeds in Mpx/s, heights in metres.\n")
    path.write_text(head + yaml.safe_dump(data, sort_keys=False, allow_unicode=True), encoding="utf-8")


__all__ = ["CASES", "MODELS", "BenchReport", "BenchRow", "BenchSettings", "best_entry", "bench_model", "cpu_info",
           "end_to_end", "run_bench", "synthetic_window", "within_tolerance", "write_table"]
