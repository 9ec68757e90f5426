"""Regenerate hard_steps.npz: states from which one step of EHBVM(12,3) is hard (docs/solver.md).

The README's run 100x longer (Kepler e = 0.6, EHBVM(12,3) imposing angular_momentum and
lrl_y, h = 0.1) aborted at step 836104, the step from t = 83610.3, whose midpoint is
2.2e-7 time units from a pericentre: Gamma is nearly singular there. This script runs
the same orbit to that time and stores the state there and at the two steps before it.

    .venv/bin/python tests/data/make_hard_steps.py
"""
from pathlib import Path

import numpy as np

import elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler

STEP = 836103   # the state before step 836104 (1-based), t = 83610.3


def main():
    result = elimfast.integrate(kepler(0.6), ehbvm(12, 3), 0.1, n_steps=STEP, conserve=["angular_momentum", "lrl_y"],
                                store_every=1)
    states = result.y[STEP - 2:STEP + 1]
    np.savez(Path(__file__).with_name("hard_steps.npz"), states=states, times=result.t[STEP - 2:STEP + 1],
             source=f"elimfast {elimfast.__version__}, steps {STEP - 2}..{STEP} of the README's run x100")
    print(f"stored {len(states)} states at t = {result.t[STEP - 2:STEP + 1]}")


if __name__ == "__main__":
    main()
