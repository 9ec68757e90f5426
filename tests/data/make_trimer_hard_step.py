"""Regenerate lj_trimer_hard_step.npz: the kernel state before a step of a user's Lennard-Jones trimer
(tests/data/lj_trimer.py, one member of its ensemble) that plain simplified Newton can take only with
a substep without imposing its angular momentum (docs/solver.md#a-substep-without-imposing).

EHBVM(8,4) imposing angular_momentum, h = 0.01, accelerate: false, max_halvings: 4, from the member's
initial state (bench/robustness.py's LJ_TRIMER_Y0): the first step whose multiplier is NaN. Which
step that is depends on the rounding of the kernels: the state is found again after a change of their
arithmetic (the first such step was step 39393 before the stages were rounded once, 2026-12).

    .venv/bin/python tests/data/make_trimer_hard_step.py
"""
import sys
from pathlib import Path

import numpy as np

import elimfast
from elimfast.integrate import Integration, SolverSettings
from elimfast.methods import ehbvm
from elimfast.problems import problem_from_file

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "bench"))
from robustness import LJ_TRIMER_Y0  # noqa: E402

CHUNK = 10_000
MAX_STEPS = 4_000_000


def main():
    problem = problem_from_file(HERE / "lj_trimer.py")
    settings = SolverSettings(accelerate=False, max_halvings=4)

    def new_run():
        return Integration(problem, ehbvm(8, 4), 0.01, n_steps=MAX_STEPS, conserve=["angular_momentum"],
                           y0=np.array(LJ_TRIMER_Y0), store_every=10 ** 9, solver=settings)

    run = new_run()
    while run.steps_done < MAX_STEPS:
        before = run.state()
        chunk = run.advance(CHUNK)
        unimposed = np.flatnonzero(np.isnan(chunk.multipliers).any(axis=1))
        if unimposed.size:
            again = new_run()
            again.restore(before)
            again.advance(int(unimposed[0]))
            state = again.state()
            np.savez(HERE / "lj_trimer_hard_step.npz", **state)
            print(f"stored the state before step {state['steps_done'] + 1} (t = {state['clock'][0]!r})")
            return
    raise SystemExit(f"no step taken without imposing in {MAX_STEPS} steps")


if __name__ == "__main__":
    main()
