"""Reader fuzz (``tests/robustness/fuzz_readers.py``) at suite size: every reader of untrusted files
accepts or raises AssetError, nothing else, on a hundred mutated inputs each.

The ARCTIC raw / misc and H2O readers have their own fuzz tests next to their readers; the
benchmark runs all of them at 1,000 cases.
"""

from __future__ import annotations

import importlib
import json
import pickle
from pathlib import Path

import pytest

pytestmark = pytest.mark.robustness

ROOT = Path(__file__).resolve().parents[2]
CASES = 100


fz = importlib.import_module("fuzz_readers")


@pytest.fixture(scope="module")
def resources(tiny_world, tmp_path_factory):
    return fz.build_resources(tmp_path_factory.mktemp("fuzz"), tiny_world, log=lambda m: None)


@pytest.mark.parametrize(
    "name", ["mano_pickle", "arctic_split", "npy_sparse", "bundle", "part_checkpoint", "run_folder", "shard"]
)
def test_reader_accepts_or_raises_asset_error(name, resources):
    tally = fz.fuzz(fz.TARGETS[name], resources, CASES, seed=0, trace_memory=False)
    assert tally.failures == []
    assert tally.cases >= 0.8 * CASES and tally.accepted + tally.refused == tally.cases
    assert tally.refused > CASES // 4  # the mutations do break the files
    assert len(tally.refusals) > 3  # ... in many different ways, each named


def test_harness_counts_an_untyped_error_as_a_failure(resources):
    def case(draw, ctx):
        if draw(fz.st.booleans()):
            raise KeyError("not typed")
        raise fz.AssetError("x.json", "typed")

    tally = fz.fuzz(fz.Target("demo", lambda res: {}, case), resources, 20, trace_memory=False)
    assert tally.refused + len(tally.failures) == tally.cases
    assert tally.refused > 0 and tally.failures and all(f.startswith("KeyError") for f in tally.failures)


def test_mutations_change_the_input_and_bombs_stay_small():
    data = b"0123456789" * 10
    seen = set()

    @fz.settings(max_examples=60, database=None, deadline=None)
    @fz.given(fz.st.data())
    def run(d):
        out = fz.mutate_bytes(d.draw, data)
        seen.add(out == data)
        bomb = fz.container_bomb(d.draw)
        assert len(pickle.dumps(bomb, protocol=2)) < 100_000  # each of <= 6 levels of <= 1000 entries stored once
        doc = fz.mutate_tree(d.draw, {"a": [1, 2, {"b": 3}], "c": "x"}, json_only=True)
        json.dumps(doc)  # JSON-only mutations stay serialisable

    run()
    assert seen == {False}  # every byte mutation changes a file without zero bytes
