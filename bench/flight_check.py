"""What the flight check costs `predict --sun auto`, once per input: reading the training squares an orthophoto
covers and correlating them (``aerialmtl.inference.sun_choice.flight_match``).

    python bench/flight_check.py ORTHO TILES [--runs 5]

TILES is the tile folder a model was trained on (its squares are cut from the training patches as ``train`` cuts
them); ORTHO the orthophoto to check. Prints the first call and the median of the next ``--runs``.
"""

from __future__ import annotations

import argparse
import statistics
import time

from aerialmtl.inference.sun_choice import flight_match
from aerialmtl.sun.flight import pick_chips
from aerialmtl.sun.record import TrainingSun
from aerialmtl.training.sun import training_area


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ortho")
    ap.add_argument("tiles")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    area = training_area(args.tiles)
    fit = TrainingSun(clear=False, reason="squares only", crs=area.crs, chips=pick_chips(area.chips),
                      chip_bands=area.bands)
    t = time.perf_counter()
    match = flight_match(args.ortho, fit)
    first = time.perf_counter() - t
    times = []
    for _ in range(args.runs):
        t = time.perf_counter()
        flight_match(args.ortho, fit)
        times.append(time.perf_counter() - t)
    print(f"{len(fit.chips)} squares, {match.chips} compared, r = {match.r}; first call {first:.3f} s, then median "
          f"{statistics.median(times):.3f} s ({min(times):.3f}–{max(times):.3f}) over {args.runs}")


if __name__ == "__main__":
    main()
