"""Writes tests/data/toda_failure_state.npz: the run state of configs/toda.yaml 100x longer
(EHBVM(12,4) imposing trace_L3, trace_L4, trace_L5 on the Toda ring of 5, h = 0.025) after
308,442 steps (t = 7711.05), just before the step whose split for alpha's rounding failed at
every depth (tests/test_step_engine.py). About 10 s.

    .venv/bin/python tests/data/make_toda_failure_state.py
"""
from pathlib import Path

import numpy as np

from elimfast.integrate import Integration
from elimfast.methods import ehbvm
from elimfast.problems import toda

STEPS = 308_442

run = Integration(toda(n=5), ehbvm(12, 4), 0.025, n_steps=400_000, conserve=["trace_L3", "trace_L4", "trace_L5"],
                  store_every=10 ** 6)
while run.steps_done < STEPS:
    run.advance(min(50_000, STEPS - run.steps_done))
    assert run.status == 0, run.status
np.savez(Path(__file__).with_name("toda_failure_state.npz"), **run.state())
