"""pytest's setup of the suite: threads, the CPU kind to run as, shared fixtures (the helpers: ``tests/helpers/``)."""

from __future__ import annotations

import os
from pathlib import Path

# Before torch loads OpenMP: threads that sleep instead of spinning while they wait. On a CPU shared with
# other jobs, spinning threads steal the cores the work needs (bench/RESULTS.md, train: 6× slower model
# steps at load 6); results do not change, only their speed. Child processes (torchrun, notebooks) inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))

#: ``pytest --cpu-kind K``: the CPU capability probe answers as on that kind of CPU (the bf16 choices of
#: ``precision: auto`` follow), in this process and in the subprocesses tests start.
#: ``avx512`` and ``avx2`` also set the kind (AERIALMTL_CPU_KIND) that ``--engine auto`` looks up in its table
#: (:mod:`aerialmtl.inference.engine_choice`); the others derive it from the bf16 flags.
#: the untracked, unignored entries at the repository root when the session started
_ROOT_BEFORE = pytest.StashKey[set[str]]()

CPU_KINDS = {"amx": "amx_bf16,avx512_bf16", "avx512bf16": "avx512_bf16", "avx512": "", "avx2": "", "none": ""}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-kind", choices=sorted(CPU_KINDS), default=None,
                     help="run as on a CPU with AMX-BF16 (amx), AVX-512-BF16 only (avx512bf16), AVX-512 without bf16 "
                          "(avx512), AVX2 only (avx2) or no native bf16 (none); default: this machine's CPU")


def pytest_configure(config: pytest.Config) -> None:
    from aerialmtl import runtime
    from aerialmtl.inference import engine_choice

    _private_stores(config)
    kind = config.getoption("--cpu-kind")
    if kind is not None:
        os.environ[runtime.CPU_FLAGS_ENV] = CPU_KINDS[kind]
        if kind in ("avx512", "avx2"):
            os.environ[engine_choice.CPU_KIND_ENV] = kind
    runtime.cpu_bf16_flags.cache_clear()
    engine_choice.cpu_kind.cache_clear()
    # the tests' own `import openvino` (importorskip, test_export) then finds it loaded without its telemetry
    try:
        runtime.import_openvino()
    except ImportError:
        pass


def _root_entries() -> set[str]:
    """Top-level entries of the checkout (names), read from the file system: no subprocess at the end of a run (a
    ``git status`` there crashed the interpreter of a full run; bench/results/commands.md, "the suite's crash")."""
    from pathlib import Path

    return {p.name for p in Path(__file__).resolve().parents[1].iterdir()}


def _ignored_at_root() -> list[str]:
    """The root-level patterns of ``.gitignore`` (``/name``, ``name``, ``*.ext``): what a run may leave there."""
    from pathlib import Path

    gitignore = Path(__file__).resolve().parents[1] / ".gitignore"
    if not gitignore.is_file():
        return []
    out = []
    for line in gitignore.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "!")) and "/" not in line.strip("/"):
            out.append(line.strip("/"))
    return out


def pytest_sessionstart(session: pytest.Session) -> None:
    if not hasattr(session.config, "workerinput") and (Path(__file__).resolve().parents[1] / ".git").exists():
        session.config.stash[_ROOT_BEFORE] = _root_entries()  # the controller only (xdist workers share the root)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Fail the run when its tests left a new file or folder at the repository root (test output belongs in
    ``tmp_path``; tests/test_repository.py says why); what ``.gitignore`` ignores at the root may appear."""
    import fnmatch

    before = session.config.stash.get(_ROOT_BEFORE, None)
    if before is None:
        return
    ignored = _ignored_at_root()
    new = sorted(n for n in _root_entries() - before if not any(fnmatch.fnmatch(n, pat) for pat in ignored))
    if new:
        import sys

        print(f"\nerror: the tests left new files at the repository root: {new}; write test output into "
              "tmp_path (tests/test_repository.py)", file=sys.stderr)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_report_header(config: pytest.Config) -> str:
    from aerialmtl import runtime
    from aerialmtl.inference.engine_choice import cpu_kind

    return f"aerialmtl CPU probe: native bf16 flags {runtime.cpu_bf16_flags() or 'none'}, kind {cpu_kind()}"


def _private_stores(config: pytest.Config) -> None:
    """The package's stores (the OpenVINO engine's converted models, the numba kernel) go to a temporary folder,
    not the user's cache. Set before any test module is imported, so that the environments test modules copy
    at import for their subprocesses (e.g. ``test_outputs.ONE_THREAD``) carry them too: a subprocess that ran on
    the user's cache met entries compiled for another CPU kind (under ``.ci/as-cpu``) and warned."""
    import shutil
    import tempfile

    root = tempfile.mkdtemp(prefix="aerialmtl-test-stores-")
    os.environ["AERIALMTL_OPENVINO_CACHE"] = os.path.join(root, "openvino-cache")
    os.environ["AERIALMTL_CACHE"] = os.path.join(root, "aerialmtl-cache")
    config.add_cleanup(lambda: shutil.rmtree(root, ignore_errors=True))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture
def kind(monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    """Set the CPU kind `--engine auto` sees (and the bf16 probe to match) for one test: ``kind("avx2")``."""
    from aerialmtl import runtime
    from aerialmtl.inference import engine_choice

    def set_kind(name: str) -> None:
        monkeypatch.setenv(engine_choice.CPU_KIND_ENV, name)
        monkeypatch.setenv(runtime.CPU_FLAGS_ENV, {"amx": "amx_bf16,avx512_bf16",
                                                   "avx512_bf16": "avx512_bf16"}.get(name, ""))
        engine_choice.cpu_kind.cache_clear()
        runtime.cpu_bf16_flags.cache_clear()

    yield set_kind
    monkeypatch.undo()
    engine_choice.cpu_kind.cache_clear()
    runtime.cpu_bf16_flags.cache_clear()
