"""Every registered method family, by looping over the registry: a new family is tested
here without editing a list. What a family declares (its multipliers, how many invariants
it may impose, whether linear ones) must be what its runs, files, config and CLI do."""
import math

import h5py

from elimfast.io.layout import multiplier_datasets
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

import elimfast
from elimfast import methods, problems, streaming
from elimfast.config import load_run_from_dict
from elimfast.errors import ParameterError
from elimfast.io.hdf5 import RunFile
from elimfast.methods import FAMILIES, IMPOSES_ANY, IMPOSES_FEWER_THAN_S, IMPOSES_NONE
from elimfast_cli.main import cli

KEPLER_INVARIANTS = ("angular_momentum", "lrl_y")
SIZES = {"r": 6, "k": 6, "s": 3}      # r = k >= s for every family


def small(family):
    return methods.get(family.name, **{p: SIZES[p] for p in family.parameters})


def imposable(method, wanted=KEPLER_INVARIANTS):
    limit = method.max_conserved()
    return tuple(wanted[:len(wanted) if limit is None else limit])


@pytest.fixture(scope="module")
def kepler():
    return problems.kepler(0.6)


@pytest.mark.parametrize("family", FAMILIES.values(), ids=lambda f: f.name)
def test_family_declares_a_consistent_record(family):
    method = small(family)
    assert method.kind is family and method.family == family.name
    assert method.name == f"{family.name.upper()}({','.join(str(SIZES[p]) for p in family.parameters)})"
    assert method.parameters == {p: SIZES[p] for p in family.parameters}
    assert family.imposes in (IMPOSES_NONE, IMPOSES_FEWER_THAN_S, IMPOSES_ANY)
    assert (family.multiplier is None) == (family.imposes == IMPOSES_NONE)
    assert family.description and family.notes and family.docs.startswith("docs/methods.md#")
    assert family.imposes_linear or family.imposes == IMPOSES_NONE or "{method}" in family.linear_refusal
    assert methods.METHODS[family.name] is family.constructor


@pytest.mark.parametrize("family", FAMILIES.values(), ids=lambda f: f.name)
def test_runs_have_the_declared_multipliers_and_keep_the_imposed_invariants(kepler, family):
    method = small(family)
    conserve = imposable(method)
    result = elimfast.integrate(kepler, method, 0.05, n_steps=40, conserve=conserve)
    count = method.multiplier_count(len(conserve))
    assert count == (0 if family.multiplier is None else len(conserve) + family.multiplier_counts_H)
    stored = {"alpha": result.alpha, "lambda": result.lam}
    for name, values in stored.items():
        if name == family.multiplier:
            assert values.shape == (40, count)
        else:
            assert values is None
    errors = result.invariant_errors()
    for name in conserve:
        assert errors[name] < 1e-13, (name, errors[name])
    if method.k > method.s:       # k = 2s nodes: H kept up to O(h^(2k+1)) per step, far below round-off here
        assert errors["H"] < 1e-12


@pytest.mark.parametrize("family", FAMILIES.values(), ids=lambda f: f.name)
def test_run_files_name_the_multipliers_as_the_method_does(kepler, family, tmp_path):
    method = small(family)
    conserve = imposable(method)
    run = elimfast.Integration(kepler, method, 0.05, 12, conserve=conserve, store_every=4)
    path = tmp_path / "run.h5"
    streaming.run_to_file(run, path, handle_signals=False, config_text="problem: {builtin: kepler}\n")
    name = method.multiplier_name(len(conserve))
    with h5py.File(path, "r") as f:
        stored = multiplier_datasets(f["steps"])   # the dimension scales and per-step counts aside
        assert stored == ([name] if name else [])
        if name:
            assert f["steps"][name].shape == (12, method.multiplier_count(len(conserve)))
            assert [str(x) for x in f["steps"][name].attrs["invariants"]] == \
                list(method.multiplier_components(conserve))
        assert f.attrs["family"] == family.name
    with RunFile(path) as run_file:
        assert run_file.multiplier_name == name


@pytest.mark.parametrize("family", FAMILIES.values(), ids=lambda f: f.name)
def test_what_a_family_may_impose_is_what_it_accepts(kepler, family):
    method = small(family)
    limit = method.max_conserved()
    too_many = ("angular_momentum", "lrl_x", "lrl_y")[:(limit or 0) + 1]
    if limit is None:
        elimfast.Integration(kepler, method, 0.1, 1, conserve=too_many)     # any number
    else:
        with pytest.raises(ParameterError) as caught:
            elimfast.Integration(kepler, method, 0.1, 1, conserve=too_many)
        assert caught.value.parameter == ("conserve" if limit == 0 else "s")
    if family.imposes == IMPOSES_NONE:
        return
    chain = problems.fpu_beta(n=4)
    linear = chain.linear_invariant_names[:1]
    if family.imposes_linear:
        elimfast.Integration(chain, method, 0.1, 1, conserve=linear)
    else:
        with pytest.raises(ParameterError, match="which is linear") as caught:
            elimfast.Integration(chain, method, 0.1, 1, conserve=linear)
        assert caught.value.parameter == "conserve" and caught.value.index == 0


@pytest.mark.parametrize("family", FAMILIES.values(), ids=lambda f: f.name)
def test_config_builds_the_family_and_maps_its_parameters_to_keys(family):
    config = {"problem": {"builtin": "kepler"}, "method": {"name": family.name.upper(),
                                                           **{p: SIZES[p] for p in family.parameters}},
              "integration": {"h": math.pi / 30, "n_steps": 3}}
    spec = load_run_from_dict(config, source="run.yaml")
    assert spec.method.name == small(family).name
    assert spec.resolved["method"] == {"name": family.name, **{p: SIZES[p] for p in family.parameters}}
    again = load_run_from_dict(yaml.safe_load(yaml.safe_dump(spec.resolved)), source="resolved.yaml")
    assert again.method.name == spec.method.name
    for parameter in family.parameters:
        bad = dict(config, method={**config["method"], parameter: 0})
        with pytest.raises(elimfast.ElimfastError) as caught:
            load_run_from_dict(bad, source="run.yaml")
        assert caught.value.key == f"method.{parameter}", str(caught.value)
        assert str(caught.value).startswith(f"run.yaml: method.{parameter}: must be >= 1")


def test_cli_lists_every_family_with_its_description():
    output = CliRunner().invoke(cli, ["methods"]).output
    for family in FAMILIES.values():
        assert f"{family.signature()}" in output and family.description in output
