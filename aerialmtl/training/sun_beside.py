"""The training area's sun fitted in a process of its own while the steps run (:class:`SunBeside`).

The sun fit after training (:func:`aerialmtl.training.sun.fit_training_sun`) is host work on the training patches
alone, independent of the network: seconds to tens of seconds (9 s on a 2048² synthetic town on 2 AMD cores),
as long as a short GPU run's steps. On a GPU the host's cores are idle while the steps run, so the trainer starts
the fit beside them (:func:`beside_steps`) and only collects it at the end.

A process, not a thread: the shadow classifier's fit (scipy's filters and labelling, L-BFGS, many small numpy
passes) holds the interpreter lock for much of its time, and the training loop needs that lock to launch the GPU's
kernels. The process is a new interpreter running :func:`main` (:data:`CHILD`): the working folder is taken off
its import path and the folder of the trainer's own ``aerialmtl`` put first, so it runs the same package and
nothing of a user's folder or script. It runs in a session (POSIX) or process group (Windows) of its own, so a
Ctrl-C at the terminal reaches the trainer, which ends it; it ends itself if the trainer dies. It writes one JSON
line: the fitted sun, or the input error that means there is none, with the log records and warnings it made,
which the trainer replays as its own. A process that fails in any other way (cannot start, ends without an answer,
gives one that cannot be read, runs longer than :data:`RESULT_TIMEOUT_S`) is reported in one warning, and the fit
is done in the trainer's process after the steps, as without a GPU.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any

from aerialmtl.errors import AerialMTLError, InputError
from aerialmtl.sun.fit import GRID_THREADS
from aerialmtl.sun.record import TrainingSun

#: Seconds the process is given to end after it is asked to stop, before it is killed.
STOP_WAIT_S = 5.0
#: Seconds the trainer waits for the answer before it ends the process and fits the sun itself (the fit takes
#: seconds to a minute: a mosaic of at most 4 Mpx).
RESULT_TIMEOUT_S = 1800.0
#: How much the process lowers its scheduling priority (``nice``, POSIX) below the trainer's.
NICE = 10
#: Thread counts the process's numerical libraries get unless the user set them: as many as its sun grid's.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")
#: What the new interpreter runs: the working folder ('' first on a ``-c`` path) off the path, then :func:`main`.
CHILD = ("import sys; sys.path[:] = [p for p in sys.path if p != '']; "
         "from aerialmtl.training.sun_beside import main; raise SystemExit(main(sys.argv[1:]))")


def beside_steps(device_type: str) -> bool:
    """Whether the sun is fitted beside the steps on this device: on an accelerator, whose steps leave the host's
    cores idle; on a CPU the steps use every core, so the fit follows them in the trainer's process (as fast, and
    no second process's memory).
    """
    return device_type != "cpu"


def _python() -> str | None:
    """This interpreter's executable, or ``None`` where it is not a Python (an application embedding one)."""
    exe = sys.executable
    name = Path(exe).name.lower() if exe else ""
    return exe if name.startswith(("python", "pypy")) else None


class SunBeside:
    """The sun fit of tile folder ``data_dir`` (its ``train`` split) running in a process of its own.

    Args:
        data_dir: the tile folder.
    """

    def __init__(self, data_dir: str | Path) -> None:
        self.data_dir = Path(data_dir)
        self.proc: subprocess.Popen[bytes] | None = None
        self.failure: str | None = None
        exe = _python()
        if exe is None:
            self.failure = f"'{sys.executable}' is not a Python interpreter to start it with"
            return
        package_parent = str(Path(__file__).resolve().parents[2])  # the folder holding this aerialmtl
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([package_parent] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        for name in THREAD_VARIABLES:
            env.setdefault(name, str(GRID_THREADS))
        own: dict[str, Any] = ({"creationflags": getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0)}
                               if os.name == "nt" else {"start_new_session": True})
        args = [exe, "-c", CHILD, str(self.data_dir.resolve()), str(logging.getLogger("aerialmtl").getEffectiveLevel()),
                str(os.getpid())]
        try:
            self.proc = subprocess.Popen(args, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, **own)
        except (OSError, ValueError) as exc:
            self.failure = f"it could not be started ({exc})"

    def result(self) -> TrainingSun:
        """The fitted sun, once the process has ended (waits for it).

        Raises:
            InputError: the area has no sun to fit (as :func:`~aerialmtl.training.sun.fit_training_sun` raises).
        """
        from aerialmtl.training.sun import fit_training_sun

        answer = self._answer()
        sun: TrainingSun | None = None
        if answer is not None:
            try:
                sun = self._read(answer)
            except InputError:
                raise
            except (AerialMTLError, ValueError, TypeError, KeyError, ImportError) as exc:
                self.failure = f"its answer could not be read ({type(exc).__name__}: {exc})"
        if sun is None:  # the process failed: said once, and the fit is done here
            warnings.warn(f"the sun fit beside the training steps failed: {self.failure}; fitting it now, after them",
                          RuntimeWarning, stacklevel=2)
            return fit_training_sun(self.data_dir)
        return sun

    @staticmethod
    def _read(answer: dict[str, Any]) -> TrainingSun:
        """The sun of an answer, its log records and warnings replayed here first (an input error raised)."""
        from aerialmtl.config import from_dict

        records = [logging.makeLogRecord(dict(r)) for r in answer.get("log", [])]
        sun = None if "input_error" in answer else from_dict(TrainingSun, answer["sun"])
        for record in records:
            logger = logging.getLogger(record.name)
            if logger.isEnabledFor(record.levelno):
                logger.handle(record)
        for w in answer.get("warnings", []):
            warnings.warn_explicit(str(w["message"]), _category(str(w["category"])), str(w["filename"]),
                                   int(w["lineno"]))
        if sun is None:
            raise InputError(str(answer["input_error"]))
        return sun

    def _answer(self) -> dict[str, Any] | None:
        """The process's JSON answer, or ``None`` (with :attr:`failure` set) when it gave none."""
        if self.proc is None:
            return None
        try:
            out, err = self.proc.communicate(timeout=RESULT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.stop()
            self.failure = f"it gave no answer within {RESULT_TIMEOUT_S:.0f} s and was ended"
            return None
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


def _category(qualified: str) -> type[Warning]:
    """The warning class named ``module:qualname`` where it can be imported and is one, else ``UserWarning``."""
    module, _, name = qualified.rpartition(":")
    try:
        found: Any = importlib.import_module(module or "builtins")
        for part in name.split("."):
            found = getattr(found, part)
    except (ImportError, AttributeError, ValueError):
        return UserWarning
    return found if isinstance(found, type) and issubclass(found, Warning) else UserWarning


class _Records(logging.Handler):
    """The log records of the fit, kept to be written with its answer."""

    def __init__(self) -> None:
        super().__init__(logging.NOTSET)
        self.kept: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.kept.append({"name": record.name, "levelno": record.levelno, "levelname": record.levelname,
                          "msg": record.getMessage(), "created": record.created, "msecs": record.msecs,
                          "pathname": record.pathname, "filename": record.filename, "module": record.module,
                          "funcName": record.funcName, "lineno": record.lineno})


def _end_with(parent: int) -> None:
    """End this process once ``parent`` (the trainer) is gone (killed outright: nobody is left to read it)."""
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(3)


def main(argv: list[str]) -> int:
    """The process: fit the sun of tile folder ``argv[0]`` (log level ``argv[1]``, trainer's pid ``argv[2]``) and
    write the answer as one JSON line on stdout.
    """
    if len(argv) > 2:
        threading.Thread(target=_end_with, args=(int(argv[2]),), daemon=True, name="aerialmtl-sun-parent").start()
    if hasattr(os, "nice"):
        try:
            os.nice(NICE)  # the steps' loop and loaders first; the trainer waiting at the end leaves it the cores
        except OSError:
            pass
    from aerialmtl.config import to_dict
    from aerialmtl.training.sun import fit_training_sun

    records = _Records()
    root = logging.getLogger("aerialmtl")
    root.addHandler(records)
    root.setLevel(int(argv[1]) if len(argv) > 1 else logging.INFO)
    answer: dict[str, Any]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            answer = {"sun": to_dict(fit_training_sun(argv[0]))}
        except InputError as exc:
            answer = {"input_error": str(exc)}
    answer["log"] = records.kept
    answer["warnings"] = [{"category": f"{w.category.__module__}:{w.category.__qualname__}", "message": str(w.message),
                           "filename": w.filename, "lineno": w.lineno} for w in caught]
    sys.stdout.write(json.dumps(answer, allow_nan=True) + "\n")
    sys.stdout.flush()
    return 0


__all__ = ["SunBeside", "beside_steps", "main"]
