"""The synthetic stream resumed exactly mid-epoch: ``HOGSADataset.state_dict`` /
``load_state_dict`` (in this process and, through torchdata's ``StatefulDataLoader``, in
DataLoader workers) and ``MixedLoader.state_dict`` / ``load_state_dict``."""

from __future__ import annotations

import itertools

import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset
from torchdata.stateful_dataloader import StatefulDataLoader

from hogsa_loader.compose import ProceduralBackgrounds
from hogsa_loader.sample import HOGSADataset, LoaderConfig
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.sample.config import with_options
from hogsa_loader.sample.mixing import MixedLoader

pytestmark = pytest.mark.usefixtures("one_thread")  # (conftest: small renders on one thread)


def _dataset(bundle, world, **kw) -> HOGSADataset:
    kw = {"batch_size": 3, "seed": 4, **kw}
    cfg = with_options(LoaderConfig(), arctic=ArcticConfig(img_res=32), render_size=40, **kw)
    return HOGSADataset(bundle, world, cfg, backgrounds=ProceduralBackgrounds())


def _key(sample) -> tuple[str, bytes]:
    """A sample's name and image bytes."""
    return sample[2]["imgname"], sample[0]["img"].numpy().tobytes()


def _index(sample) -> int:
    """-1 - the stream index of a synthetic sample (its image name ends in the index)."""
    return -1 - int(sample[2]["imgname"].rsplit("/", 1)[1].split(".")[0])


def test_a_stream_resumed_from_its_state_yields_what_it_would_have(untrained_bundle, tiny_world):
    ds = _dataset(untrained_bundle, tiny_world)
    assert ds.state_dict()["batch"] == -1  # before an iteration: the shard's start
    it = iter(ds)
    # (these settings drop many samples: kept indices 0 | 2 3 | 5 6 | 8 | - | 14 | - | 19 21 22)
    first = [next(it) for _ in range(5)]  # up to index 6, the first kept one of render batch 2
    state = ds.state_dict()
    assert (state["batch"], state["skip"], state["num_shards"]) == (2, 1, 1)
    assert [-1 - _index(s) for s in first] == [0, 2, 3, 5, 6]
    first = [_key(s) for s in first]
    rest = [_key(next(it)) for _ in range(4)]
    again = _dataset(untrained_bundle, tiny_world)
    again.load_state_dict(dict(state))
    assert [_key(s) for s in itertools.islice(again, 4)] == rest
    assert not set(first) & set(rest)
    whole = [_key(s) for s in itertools.islice(_dataset(untrained_bundle, tiny_world), 9)]
    assert whole == first + rest
    # after the last kept sample of a render batch, the state points at the next batch
    ds = _dataset(untrained_bundle, tiny_world)
    it = iter(ds)
    [next(it) for _ in range(4)]
    assert (ds.state_dict()["batch"], ds.state_dict()["skip"]) == (2, 0)


def test_a_state_of_other_settings_is_refused(untrained_bundle, tiny_world):
    ds = _dataset(untrained_bundle, tiny_world)
    next(iter(ds))
    state = ds.state_dict()
    with pytest.raises(ValueError, match="seed=4.*seed=5"):
        _dataset(untrained_bundle, tiny_world, seed=5).load_state_dict(state)
    with pytest.raises(ValueError, match="batch_size"):
        _dataset(untrained_bundle, tiny_world, batch_size=2).load_state_dict(state)
    with pytest.raises(ValueError, match="not a HOGSADataset stream state"):
        ds.load_state_dict({"epoch": 0})
    moved = _dataset(untrained_bundle, tiny_world)
    moved.load_state_dict(state)
    moved.set_epoch(1)  # a state of epoch 0 dropped: the next iteration starts epoch 1
    assert (moved.state_dict()["epoch"], moved.state_dict()["batch"]) == (1, -1)
    other = _dataset(untrained_bundle, tiny_world)
    other.load_state_dict({**state, "num_shards": 2})
    with pytest.raises(ValueError, match="over 2 shards.*has 1"):
        next(iter(other))


def test_stateful_dataloader_workers_resume_their_shards(untrained_bundle, tiny_world):
    def loader(state=None):
        dl = StatefulDataLoader(_dataset(untrained_bundle, tiny_world), batch_size=None, num_workers=2)
        if state is not None:
            dl.load_state_dict(state)
        return dl

    dl = loader()
    it = iter(dl)
    first = [_key(next(it)) for _ in range(5)]
    state = dl.state_dict()
    rest = [_key(next(it)) for _ in range(5)]
    del it
    resumed = [_key(s) for s in itertools.islice(loader(state), 5)]
    assert resumed == rest and not set(first) & set(rest)


def test_mixed_loader_resumes_mid_epoch_without_drawing_the_used_samples_again(untrained_bundle, tiny_world):
    real = DataLoader(TensorDataset(torch.arange(24)), batch_size=4, shuffle=True, generator=torch.Generator())

    def mixed():
        real.generator.manual_seed(0)  # the real order of the epoch
        syn = _dataset(untrained_bundle, tiny_world)
        return MixedLoader(real, syn, 0.5, collate_fn=lambda xs: [torch.tensor([_index(x) for x in xs])]), syn

    def parts(batch):  # real sample values (>= 0), then synthetic sample indices as -1 - index
        return batch[0].tolist()

    whole = [parts(b) for b in mixed()[0]]
    loader, syn = mixed()
    it = iter(loader)
    head = [parts(next(it)) for _ in range(3)]
    state = loader.state_dict()
    assert (state["batches"], state["synthetic_taken"]) == (3, 6) and state["synthetic"][0]["batch"] == 3
    again, syn2 = mixed()
    again.load_state_dict(state)
    rendered = []
    syn2.render = (lambda render: lambda plan: rendered.append(plan.indices) or render(plan))(syn2.render)
    tail = [parts(b) for b in again]
    assert head + tail == whole and len(whole) == 12  # 24 real samples, 2 per batch
    assert again.state_dict()["batches"] == 12 and again.state_dict()["synthetic_taken"] == 24
    assert rendered[0] == (9, 10, 11)  # resumed at render batch 3: samples 0-8 not rendered again
    with pytest.raises(ValueError, match="not a MixedLoader state"):
        again.load_state_dict({"epoch": 0, "batches": -1, "synthetic_taken": 0})
    with pytest.raises(ValueError, match="taken over 2 process"):
        again.load_state_dict({**state, "synthetic": [None, None]})
    # PyTorch Lightning's order: the state loaded, the loader's iterator made, set_epoch of the
    # same epoch, then the first batch: the resume stands (and state_dict says it meanwhile)
    lit, _ = mixed()
    lit.load_state_dict(state)
    it = iter(lit)
    lit.sampler.set_epoch(0)
    assert lit.state_dict() == state
    assert parts(next(it)) == whole[3]
    other, _ = mixed()
    other.load_state_dict(state)
    other.sampler.set_epoch(1)  # another epoch: the resume is dropped
    assert other.state_dict()["batches"] == 0 and other.epoch == 1
