"""Tiny generated sets shared by the benchmark tests.

Paper: 96x72, 3 images + 1 negative. Novel: 160x120, one image per object at N = 2
+ 1 negative per object. Multi: 160x120, one image per object (bracket, clamp) with
three instances among N = 2 clutter objects, no negatives.
"""

import dataclasses
from pathlib import Path

import pytest

from viewloc_bench import povray, sets


def tiny_paper_spec() -> sets.SetSpec:
    return dataclasses.replace(sets.paper_spec(1, 1, scale=0.25), n_values=(0, 4, 9))


def _generated(tmp_path_factory: pytest.TempPathFactory, spec: sets.SetSpec) -> Path:
    """``spec`` generated with seed 7 into a fresh folder (skipped without POV-Ray)."""
    if povray.povray_executable() is None:
        pytest.skip("povray not installed")
    root = tmp_path_factory.mktemp(f"bench_sets_{spec.name}")
    return sets.generate(spec, 7, root, workers=3, log=None)


@pytest.fixture(scope="session")
def tiny_paper_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _generated(tmp_path_factory, tiny_paper_spec())


def tiny_novel_spec() -> sets.SetSpec:
    return dataclasses.replace(sets.novel_spec(1, 1, scale=0.25), n_values=(2,))


@pytest.fixture(scope="session")
def tiny_novel_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _generated(tmp_path_factory, tiny_novel_spec())


def tiny_multi_spec() -> sets.SetSpec:
    return dataclasses.replace(sets.multi_spec(1, 0, scale=0.25), n_values=(2,))


@pytest.fixture(scope="session")
def tiny_multi_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _generated(tmp_path_factory, tiny_multi_spec())
