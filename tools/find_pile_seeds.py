"""Search generator seeds whose pile volume is close to the paper's Table 1 (run once; result in
sitl/world/stockpile.py PAPER_PILES). Usage: python -m tools.find_pile_seeds [--tolerance-pct 1]."""

from __future__ import annotations

import argparse

from firmware_py.core.storage import Storage
from sitl.world.stockpile import PAPER_PILES, PileSpec, generate


def find_seed(zero_edges: bool, target_m3: float, tolerance_pct: float, max_seed: int = 1000) -> tuple[int, float]:
    storage = Storage()
    for seed in range(max_seed):
        v = generate(PileSpec(seed=seed, zero_edges=zero_edges), storage).volume_m3
        if abs(v - target_m3) / target_m3 * 100 <= tolerance_pct:
            return seed, v
    raise SystemExit(f"no seed below {max_seed} within {tolerance_pct} % of {target_m3}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--tolerance-pct", type=float, default=1.0)
    args = ap.parse_args(argv)
    for name, p in PAPER_PILES.items():
        seed, v = find_seed(p["zero_edges"], p["table1_volume_m3"], args.tolerance_pct)
        err = (v - p["table1_volume_m3"]) / p["table1_volume_m3"] * 100
        print(f"pile {name}: seed {seed}  volume {v:.1f} m^3  ({err:+.2f} % vs Table 1)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
