"""`aerialmtl bench`: model-alone and end-to-end Mpx/s of every engine × precision on this CPU (a thin command over
:func:`aerialmtl.inference.cpu_bench.run_bench`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import click

from aerialmtl.cli.options import option, output_path

_CASES = ("torch/fp32", "torch/bf16", "openvino/fp32", "openvino/bf16", "openvino/int8")


def _split(ctx: click.Context, param: click.Parameter, value: str) -> tuple[str, ...]:
    items = tuple(v.strip() for v in value.split(",") if v.strip())
    allowed = ("full", "small") if param.name == "models" else _CASES
    bad = [v for v in items if v not in allowed]
    if bad or not items:
        raise click.BadParameter(f"expected a comma-separated list of {', '.join(allowed)}, got {value!r}", ctx, param)
    return items


@click.command(name="bench")
@option("--models", default="full,small", show_default=True, callback=_split,
        help="Models: full (the paper's DenseNet-121 D3-Net) and/or small (the small-area config's).")
@option("--cases", default=",".join(_CASES), show_default=True, callback=_split,
        help="engine/precision pairs (int8: OpenVINO quantised by NNCF, model alone, when NNCF is installed).")
@option("--window", type=click.IntRange(min=32), default=512, show_default=True,
        help="Side of the model-alone windows (pixels).")
@option("--windows", type=click.IntRange(min=1), default=2, show_default=True,
        help="Model-alone windows timed per case (after one warm-up window).")
@option("--size", type=click.IntRange(min=0), default=1024, show_default=True,
        help="Side of the synthetic orthophoto predicted end to end (T = 1, whole process); 0 = model alone only.")
@option("--threads", default="auto", show_default=True, help="Inference threads, as for predict.")
@option("--workdir", type=output_path(file_okay=False), default=None,
        help="Keep checkpoints, rasters, the OpenVINO cache and outputs here [default: a temporary folder].")
@option("--json", "json_out", type=output_path(dir_okay=False), default=None, help="Also write the report as JSON.")
@option("--write-table", "table", type=output_path(dir_okay=False), default=None,
        help="Set this CPU kind's entry (the fastest full-D3-Net engine × precision within the tolerances) in "
             "this engine-choice table, e.g. aerialmtl/resources/engine_choice.yaml.")
def bench(models: tuple[str, ...], cases: tuple[str, ...], window: int, windows: int, size: int, threads: str,
          workdir: Path | None, json_out: Path | None, table: Path | None) -> None:
    """Measure every engine × precision on this CPU, so numbers of any CPU can be compared and sent.

    Prints the CPU (name, family/model, kind, load), then per model and case the model-alone Mpx/s with its
    difference from torch fp32, and the end-to-end Mpx/s of `aerialmtl predict`. Takes minutes on 2 cores.
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.inference.cpu_bench import (
        BenchRow,
        BenchSettings,
        best_entry,
        cpu_info,
        run_bench,
        within_tolerance,
        write_table,
    )

    cpu = cpu_info()
    click.echo(f"cpu: {cpu['name']} (family {cpu.get('cpu_family', '?')} model {cpu.get('model', '?')}), kind "
               f"{cpu['kind']}{' (ONEDNN_MAX_CPU_ISA=' + cpu['isa_cap'] + ')' if cpu['isa_cap'] else ''}, "
               f"{cpu['cores']} cores, flags {' '.join(cpu.get('flags', []))}; load {os.getloadavg()[0]:.2f}")
    click.echo(f"{'model':<6} {'engine':<9} {'prec':<5} {'stage':<11} {'Mpx/s':>8} {'s':>8} {'|Δh| m':>8} "
               f"{'class =':>8} ok  load")

    def num(value: float | None, spec: str) -> str:
        return format(value, spec) if value is not None else "-"

    def show(r: BenchRow) -> None:
        click.echo(f"{r.model:<6} {r.engine:<9} {r.precision:<5} {r.stage:<11} {num(r.mpx_s, '8.4f'):>8} "
                   f"{num(r.seconds, '8.2f'):>8} {num(r.height_mae_m, '8.4f'):>8} {num(r.class_agreement, '8.4f'):>8}"
                   f" {('yes' if within_tolerance(r) else 'no ') if r.stage == 'model' and r.mpx_s else '   '} "
                   f"{r.load[0]:.1f}→{r.load[1]:.1f}{'  ' + r.note if r.note else ''}")

    pairs = tuple((engine, precision) for engine, _, precision in (c.partition("/") for c in cases))
    settings = BenchSettings(models=models, cases=pairs,
                             window=window, windows=windows, size=size, threads=threads, workdir=workdir)
    report = run_bench(settings, on_row=show)
    if json_out is not None:
        json_out.write_text(json.dumps(report.to_dict(), indent=2), encoding="utf-8")
        click.echo(f"report: {json_out}")
    if table is not None:
        try:
            entry = best_entry(report)
        except ValueError as exc:
            raise click.ClickException(f"{exc}; {table} is unchanged (measure --models full with more cases)") from None
        write_table(table, cpu["kind"], entry)
        click.echo(f"{table}: kind {cpu['kind']} → {entry.engine} {entry.precision} ({entry.measured})")
