"""Sub-block gathers of matrix stacks and the navigation options derived from a model's own dynamics (issue 13)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from covtool.io.model_file import load_model
from covtool.lincov.dynamics import Context, error_dynamics, NavOptions, with_nav_options
from covtool.lincov.stacks import gather
from covtool.nav.trajectory.profiles import land_vehicle

SDINS58 = Path(__file__).resolve().parents[1] / "models" / "sdins58.toml"


@pytest.mark.parametrize("rows, cols", [([3, 0, 5], None), ([1, 2, 3], [0, 1]), ([4, 4, 1], [5, 0, 2, 2]),
                                        ([-1, 0], [-2]), (np.arange(6), None), ([], [1, 2])])
def test_gather_equals_the_fancy_index_and_is_a_contiguous_copy(rows, cols):
    X = np.random.default_rng(3).normal(size=(7, 6, 6))
    c = rows if cols is None else cols
    want = X[:, np.asarray(rows, int)][:, :, np.asarray(c, int)]
    got = gather(X, rows, cols)
    assert got.shape == want.shape and np.array_equal(got, want)
    assert got.flags.c_contiguous and not np.shares_memory(got, X)


def test_gather_takes_non_contiguous_and_unbatched_input():
    X = np.random.default_rng(4).normal(size=(6, 5, 8))
    V = X[::2, :, ::2]                                          # strided view, (3, 5, 4)
    assert np.array_equal(gather(V, [4, 0], [3, 1]), V[:, [4, 0]][:, :, [3, 1]])
    assert np.array_equal(gather(X[0], [1, 2], [7]), X[0][[1, 2]][:, [7]])


def test_gather_errors():
    with pytest.raises(ValueError, match="needs a stack of matrices"):
        gather(np.zeros(3), [0])
    with pytest.raises(IndexError, match="row index out of range for a stack of 3 × 4 matrices"):
        gather(np.zeros((2, 3, 4)), [3], [0])
    with pytest.raises(IndexError, match="column index out of range"):
        gather(np.zeros((2, 3, 4)), [0], [-5])


@pytest.mark.parametrize("options", [NavOptions(coriolis=False), NavOptions(couple_vertical=False),
                                     NavOptions(coriolis=False, couple_vertical=False), NavOptions()])
def test_nav_options_derived_from_the_models_dynamics_equal_a_fresh_build(options):
    """Only F's 10 × 10 navigation block depends on the options: the derived F, Q_c and noise are exact."""
    model = load_model(SDINS58)
    s = land_vehicle(dt=1.0).sample(np.linspace(0.0, 1800.0, 301))
    ctx = Context.from_trajectory(s)
    base = error_dynamics(model, ctx)
    want = error_dynamics(model, ctx, options)
    got = with_nav_options(base, ctx, options)
    assert np.array_equal(got.F, want.F)
    assert np.array_equal(got.Qc, want.Qc)
    assert [x.name for x in got.noise] == [x.name for x in want.noise]
    if options != NavOptions():
        assert got.F is not base.F and not np.array_equal(got.F[:, :10, :10], base.F[:, :10, :10])
        assert np.array_equal(got.F[:, :, 10:], base.F[:, :, 10:]) and np.array_equal(got.F[:, 10:], base.F[:, 10:])


@pytest.mark.parametrize("rows, cols", [([0, 5, 12, 3], None), ([9, 10, 57, 1], [2, 40, 9, 0, 0]),
                                        (np.arange(10), np.arange(10, 20)), ([30, 20], [11, 12]),
                                        ([-58, -49, 11], [-1, 3]), (np.arange(58), None)])
def test_options_dynamics_sub_blocks_equal_those_of_the_full_stack(rows, cols):
    """A reduced filter's rows of F under other options are gathered without building the (N, 58, 58) copy.

    The sub-block mixes the replaced navigation block (rows and columns below 10) with the base F's
    sensor entries; it must equal the same gather from the fresh build (error_dynamics under the
    options), element for element, and leave the full stack unbuilt until ``F`` itself is read.
    """
    model = load_model(SDINS58)
    s = land_vehicle(dt=1.0).sample(np.linspace(0.0, 600.0, 61))
    ctx = Context.from_trajectory(s)
    options = NavOptions(coriolis=False, couple_vertical=False)
    got = with_nav_options(error_dynamics(model, ctx), ctx, options)
    want = error_dynamics(model, ctx, options).F
    c = rows if cols is None else cols
    block = got.F_block(rows, cols)
    assert got._F is None                                     # not built by a gather
    assert np.array_equal(block, want[:, np.asarray(rows)][:, :, np.asarray(c)])
    assert block.flags.c_contiguous
    assert np.array_equal(got.F, want) and np.array_equal(got.F_block(rows, cols), block)   # after the build too


@pytest.mark.parametrize("a, b", [(0, 60), (0, 1), (17, 42), (59, 60), (30, 30)])
def test_options_dynamics_step_runs_equal_those_of_the_full_stack(a, b):
    """F under other options, steps a … b−1 (the impact table's chunked transition), without the full copy.

    Equal element for element to the rows of the fresh build (error_dynamics under the options), and
    C-contiguous; the base dynamics' own runs are views of its F.
    """
    model = load_model(SDINS58)
    s = land_vehicle(dt=1.0).sample(np.linspace(0.0, 600.0, 61))
    ctx = Context.from_trajectory(s)
    options = NavOptions(coriolis=False, couple_vertical=False)
    base = error_dynamics(model, ctx)
    got = with_nav_options(base, ctx, options)
    want = error_dynamics(model, ctx, options).F
    run = got.F_steps(a, b)
    assert got._F is None                                     # not built by a run of steps
    assert run.shape == (b - a, 58, 58) and run.flags.c_contiguous
    assert np.array_equal(run, want[a:b])
    assert not np.array_equal(run[:, :10, :10], base.F[a:b, :10, :10]) or a == b
    assert np.shares_memory(base.F_steps(a, b), base.F) or a == b
    assert np.array_equal(got.F[a:b], run) and np.array_equal(got.F_steps(a, b), run)   # after the build too
