"""Turn experiments/hostile_part3/run.py's JSON lines into the table of experiments/hostile_part3/README.md
(command, what happened, the automatic verdict).

Usage: ``python -m experiments.hostile_part3.to_md RESULTS.jsonl > table.md``.

Automatic verdict: ``FAIL`` for a hang (the case passed its timeout), "Error: unexpected", a traceback, "Aborted"
or an exit status other than 0, 1 and 2; otherwise ``ok``. Whether the outcome is the *right* one (exit 0 with a
warning, or a refusal naming the cause) is read by hand and written in the note column of the .md.
"""

from __future__ import annotations

import json
import sys


def verdict(rec: dict) -> str:
    """``ok`` or ``FAIL (why)`` for one case (see the module docstring)."""
    bad = [k for k in ("unexpected", "traceback", "aborted") if rec.get(k)]
    if rec["rc"] == "HANG":
        bad.append("hang")
    elif rec["rc"] not in (0, 1, 2):
        bad.append(f"exit {rec['rc']}")
    return "ok" if not bad else f"FAIL ({', '.join(bad)})"


def main() -> None:
    """Print the table."""
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        return
    rows = [json.loads(line) for line in open(sys.argv[1], encoding="utf-8") if line.strip()]
    print("| # | case | command (env) | exit | s | what it said (last line) | verdict |")
    print("|---|---|---|---|---|---|---|")
    for n, rec in enumerate(rows, 1):
        env = " ".join(f"{k}={v!r}" for k, v in rec["env"].items())
        cmd = f"{rec['prefix'] + ' ' if rec['prefix'] else ''}python {rec['cmd']}" + (f" ({env})" if env else "")
        said = (rec["stderr"] or rec["stdout"] or [""])[-1]
        said = " ".join(said.split()).replace("|", "\\|")
        if len(said) > 400:
            said = said[:400] + " …"
        print(f"| {n} | {rec['case']} | `{cmd.replace('|', '/')}` | {rec['rc']} | {rec['s']} | {said} | "
              f"{verdict(rec)} |")


if __name__ == "__main__":
    main()
