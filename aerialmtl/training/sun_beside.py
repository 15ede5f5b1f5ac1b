"""The training area's sun fitted in a process of its own while the steps run (:class:`SunBeside`).

The sun fit after training (:func:`aerialmtl.training.sun.fit_training_sun`) is host work on the training patches
alone, independent of the network: seconds to tens of seconds (9 s on a 2048² synthetic town on 2 AMD cores),
as long as a short GPU run's steps. On a GPU the host's cores are idle while the steps run, so the trainer starts
the fit beside them (:func:`beside_steps`) and only collects it at the end.

A process, not a thread: the fit's numpy and scipy passes would hold the interpreter lock that the training loop
needs to launch the GPU's kernels. The process is ``python -m aerialmtl.training.sun_beside TILE_FOLDER`` (a new
interpreter, so nothing of a user's own script is run again in it), in a session of its own (a Ctrl-C at the
terminal reaches the trainer, which ends it); it writes one JSON line: the fitted sun, or the input error that
means there is none, and the log records and warnings it made, which the trainer replays as its own. A process
that fails in any other way (or cannot be started) is reported in one warning, and the fit is done in the
trainer's process after the steps, as without a GPU.
"""

from __future__ import annotations

import builtins
import json
import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

from aerialmtl.errors import InputError
from aerialmtl.sun.fit import GRID_THREADS
from aerialmtl.sun.record import TrainingSun

log = logging.getLogger(__name__)

#: Seconds the process is given to end after it is asked to stop, before it is killed.
STOP_WAIT_S = 5.0
#: How much the process lowers its scheduling priority (``nice``) below the trainer's.
NICE = 10


def beside_steps(device_type: str) -> bool:
    """Whether the sun is fitted beside the steps on this device: on an accelerator, whose steps leave the host's
    cores idle; on a CPU the steps use every core, so the fit follows them in the trainer's process (as fast, and
    no second process's memory).
    """
    return device_type != "cpu"


class SunBeside:
    """The sun fit of tile folder ``data_dir`` (its ``train`` split) running in a process of its own.

    Args:
        data_dir: the tile folder.
    """

    def __init__(self, data_dir: str | Path) -> None:
        self.data_dir = Path(data_dir)
        self.proc: subprocess.Popen[bytes] | None = None
        self.failure: str | None = None
        try:
            threads = str(GRID_THREADS)  # its BLAS as many threads as its sun grid: the other cores stay the steps'
            env = {**os.environ, "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads,
                   "MKL_NUM_THREADS": threads,
                   "PYTHONSAFEPATH": "1"}  # `-m` would put the working folder first on the path (Python ≥ 3.11)
            self.proc = subprocess.Popen([sys.executable, "-m", __name__, str(self.data_dir.resolve())], env=env,
                                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         start_new_session=True)
        except OSError as exc:
            self.failure = f"it could not be started ({exc})"

    def result(self) -> TrainingSun:
        """The fitted sun, once the process has ended (waits for it).

        Raises:
            InputError: the area has no sun to fit (as :func:`~aerialmtl.training.sun.fit_training_sun` raises).
        """
        from aerialmtl.training.sun import fit_training_sun

        answer = self._answer()
        if answer is None:  # the process failed: said once, and the fit is done here
            warnings.warn(f"the sun fit beside the training steps failed: {self.failure}; fitting it now, after them",
                          RuntimeWarning, stacklevel=2)
            return fit_training_sun(self.data_dir)
        for level, name, message in answer.get("log", []):
            logging.getLogger(str(name)).log(int(level), "%s", message)
        for category, message in answer.get("warnings", []):
            kind = getattr(builtins, str(category), None)  # a built-in category as it was, any other a UserWarning
            warnings.warn(str(message), kind if isinstance(kind, type) and issubclass(kind, Warning) else UserWarning,
                          stacklevel=2)
        if "input_error" in answer:
            raise InputError(str(answer["input_error"]))
        from aerialmtl.config import from_dict

        return from_dict(TrainingSun, answer["sun"])

    def _answer(self) -> dict[str, Any] | None:
        """The process's JSON answer, or ``None`` (with :attr:`failure` set) when it gave none."""
        if self.proc is None:
            return None
        try:
            out, err = self.proc.communicate()
        except BaseException:  # Ctrl-C while waiting for it: the process is ended, not left running
            self.stop()
            raise
        self.proc = None
        lines = out.decode(errors="replace").strip().splitlines()
        try:
            answer = json.loads(lines[-1]) if lines else None
        except ValueError:
            answer = None
        if isinstance(answer, dict) and ("sun" in answer or "input_error" in answer):
            return answer
        tail = " ".join(err.decode(errors="replace").strip().splitlines()[-3:])
        self.failure = f"its process gave no result ({tail or 'no message'})"
        return None

    def stop(self) -> None:
        """End the process if it still runs (training failed or was interrupted); nothing is stored."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


class _Records(logging.Handler):
    """The log records of the fit, kept to be written with its answer."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.kept: list[tuple[int, str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.kept.append((record.levelno, record.name, record.getMessage()))


def main(argv: list[str]) -> int:
    """The process: fit the sun of tile folder ``argv[0]``, write the answer as one JSON line on stdout."""
    try:
        os.nice(NICE)  # the steps' loop and loaders first; the trainer waiting at the end leaves it the cores
    except OSError:
        pass
    from aerialmtl.config import to_dict
    from aerialmtl.training.sun import fit_training_sun

    records = _Records()
    root = logging.getLogger("aerialmtl")
    root.addHandler(records)
    root.setLevel(logging.INFO)
    answer: dict[str, Any]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            answer = {"sun": to_dict(fit_training_sun(argv[0]))}
        except InputError as exc:
            answer = {"input_error": str(exc)}
    answer["log"] = records.kept
    answer["warnings"] = [(w.category.__name__, str(w.message)) for w in caught]
    sys.stdout.write(json.dumps(answer, allow_nan=True) + "\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":  # pragma: no cover - run as a process (tests/test_sun_train.py)
    raise SystemExit(main(sys.argv[1:]))
