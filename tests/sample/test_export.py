"""WebDataset export of SynthFrames: round trip, resume, rank split, ARCTIC samples."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import signal
import subprocess
import sys
import tarfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import make_frame
from torch.utils.data import DataLoader

from hogsa_loader.errors import AssetError
from hogsa_loader.sample.augment import sample_aug_params
from hogsa_loader.sample.export import (
    ExportMismatchError,
    SynthShardDataset,
    SynthShardSamples,
    decode_frame,
    encode_frame,
    expand_shards,
    export_settings,
    frame_to_arctic_sample,
    iter_tar_samples,
    rebuild_index,
    shard_name,
    write_shards,
)
from hogsa_loader.sample.export.codec import split_member_name
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.synth import frame_to_sample, source_scale
from hogsa_loader.sample.targets import SAMPLE_META_KEYS, SAMPLE_TARGET_KEYS, make_arctic_sample

S = 48  # the side of conftest.make_frame's images
NUM, SHARD = 7, 4  # two shards: 4 + 3 samples


def frames_for(calls: list):
    def fn(shard: int):
        calls.append(shard)
        for i in range(shard * SHARD, min((shard + 1) * SHARD, NUM)):
            yield make_frame(i)

    return fn


def assert_same_frame(a: SynthFrame, b: SynthFrame) -> None:
    assert a.image.shape == b.image.shape and a.image.dtype == b.image.dtype == np.uint8
    assert np.abs(a.image.astype(int) - b.image.astype(int)).mean() < 2.0
    assert np.abs(a.image.astype(int) - b.image.astype(int)).max() <= 16
    assert np.abs(a.alpha - b.alpha).max() <= 0.5 / 255 + 1e-7 and b.alpha.dtype == np.float32
    assert np.abs(a.part_alpha - b.part_alpha).max() <= 0.5 / 255 + 1e-7
    for x, y in ((a.bbox, b.bbox), (a.K_full, b.K_full)):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    assert a.image_size == b.image_size
    for ha, hb in ((a.right, b.right), (a.left, b.left)):
        for f in ("pose48", "betas", "j3d_full", "j2d"):
            x, y = getattr(ha, f), getattr(hb, f)
            assert x.dtype == y.dtype and np.array_equal(x, y), f
        assert ha.valid == hb.valid
    for f in ("kp3d_full", "bbox3d_full", "kp2d", "bbox2d", "kp_bottom_cano"):
        x, y = getattr(a.obj, f), getattr(b.obj, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f
    assert (a.obj.name, a.obj.radian, a.obj.valid) == (b.obj.name, b.obj.radian, b.obj.valid)
    assert a.imgname == b.imgname
    assert json.loads(json.dumps(a.meta, default=int)) == b.meta
    assert a.extra_targets.keys() == b.extra_targets.keys()  # e.g. the interaction field
    for k, x in a.extra_targets.items():
        y = b.extra_targets[k]
        assert type(x) is type(y) and np.array_equal(x, y) and getattr(x, "dtype", None) == getattr(y, "dtype", None), k


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    calls: list = []
    res = write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 3})
    assert calls == [0, 1] and res["complete"] and res["samples"] == NUM
    return out


def test_layout_and_members(export_dir):
    assert sorted(p.name for p in export_dir.glob("*.tar")) == [shard_name(0), shard_name(1)]
    index = json.loads((export_dir / "index.json").read_text())
    assert index["complete"] and index["num_samples_written"] == NUM and index["info"] == {"seed": 3}
    assert [s["count"] for s in index["shards"]] == [4, 3]
    per = json.loads((export_dir / "synth-000001.index.json").read_text())
    assert per["first"] == 4 and per["last"] == 6 and per["keys"][0] == "0000000004"
    with tarfile.open(export_dir / shard_name(0)) as tar:
        names = tar.getnames()
        assert names[:5] == [
            "0000000000.jpg",
            "0000000000.alpha.png",
            "0000000000.parts.png",
            "0000000000.labels.npz",
            "0000000000.json",
        ]
        z = np.load(io.BytesIO(tar.extractfile("0000000000.labels.npz").read()), allow_pickle=False)
        assert z["right.j2d"].shape == (21, 2) and "obj.kp3d_full" in z.files
        info = json.loads(tar.extractfile("0000000000.json").read())
    assert info["imgname"] == make_frame(0).imgname and info["object"] == "box"
    assert info["index"] == 0 and info["image_size"] == [640, 480] and len(info["K_full"]) == 3
    assert [k for k, _ in iter_tar_samples(export_dir / shard_name(1))] == ["0000000004", "0000000005", "0000000006"]


def test_round_trip_exact(export_dir):
    frames = list(SynthShardDataset(export_dir))
    assert len(frames) == NUM
    for i, f in enumerate(frames):
        assert_same_frame(make_frame(i), f)
    # brace pattern and explicit list read the same
    pat = str(export_dir / "synth-{000000..000001}.tar")
    assert len(expand_shards(pat)) == 2
    assert [f.imgname for f in SynthShardDataset(pat)] == [f.imgname for f in frames]
    # 16-bit alpha and lossless image
    m = encode_frame(make_frame(2), "k", image_format="png", alpha_bits=16)
    back = decode_frame({n.split(".", 1)[1]: b for n, b in m.items()})
    assert np.array_equal(back.image, make_frame(2).image)
    assert np.abs(back.alpha - make_frame(2).alpha).max() <= 0.5 / 65535 + 1e-7


def test_resume_after_interruption(tmp_path, export_dir):
    out = tmp_path / "e"
    calls: list = []
    write_shards(frames_for(calls), out, NUM, SHARD, progress=False)
    first = (out / shard_name(0)).read_bytes()
    assert first == (export_dir / shard_name(0)).read_bytes()  # byte-identical exports
    # shard 1 lost; an exception while rewriting it removes its temp file, a SIGKILL leaves one
    (out / shard_name(1)).unlink()

    def crashing(shard):
        yield make_frame(4)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_shards(crashing, out, NUM, SHARD, progress=False)
    assert not (out / shard_name(1)).exists() and not list(out.glob(".synth-000001.tar.*.tmp"))
    assert not json.loads((out / "index.json").read_text())["complete"]
    (out / ".synth-000001.tar.999999.0123abcd.tmp").write_bytes(b"torn")
    calls.clear()
    res = write_shards(frames_for(calls), out, NUM, SHARD, progress=False)
    assert calls == [1] and res["skipped"] == [0] and res["complete"]
    assert not list(out.glob(".synth-*.tmp"))
    assert (out / shard_name(0)).read_bytes() == first
    for i, f in enumerate(SynthShardDataset(out)):
        assert_same_frame(make_frame(i), f)
    # a truncated shard (size disagrees with its index) is rewritten
    data = (out / shard_name(1)).read_bytes()
    (out / shard_name(1)).write_bytes(data[: len(data) // 2])
    calls.clear()
    write_shards(frames_for(calls), out, NUM, SHARD, progress=False)
    assert calls == [1]


def test_a_killed_export_reads_as_incomplete(tmp_path):
    """SIGKILL in the middle of a fresh export (no finally block runs): its index.json, written
    before the first shard, says incomplete, so the readers refuse it; the next run completes it."""
    out = tmp_path / "killed"
    script = f"""
import os, signal, sys
sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})
from conftest import make_frame
from hogsa_loader.sample.export import write_shards

def frames(shard):
    for i in range(shard * {SHARD}, min((shard + 1) * {SHARD}, {NUM})):
        if shard == 1:
            os.kill(os.getpid(), signal.SIGKILL)
        yield make_frame(i)

write_shards(frames, {str(out)!r}, {NUM}, {SHARD}, progress=False)
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert (out / shard_name(0)).is_file() and not (out / shard_name(1)).exists()
    with pytest.raises(AssetError, match="incomplete"):
        SynthShardDataset(out)
    with pytest.raises(AssetError, match="no complete shard"):  # (the index lists what it had verified)
        expand_shards(out, incomplete=True)
    calls: list = []
    assert write_shards(frames_for(calls), out, NUM, SHARD, progress=False)["complete"]  # resumed
    assert calls == [1] and len(list(SynthShardDataset(out))) == NUM


def test_resume_refuses_another_exports_shards(tmp_path, export_dir):
    """A folder holding shards of another export (seed, num, shard size, format) is refused,
    naming the shard and the difference; overwrite=True rewrites what differs and removes
    shard files past the last one, so the reader sees exactly this export."""
    out = tmp_path / "m"
    calls: list = []
    write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 3, "world_size": 1})
    # world_size does not change the samples: a resume with another one skips everything
    calls.clear()
    res = write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 3, "world_size": 4})
    assert calls == [] and res["complete"]
    with pytest.raises(ExportMismatchError, match=r"synth-000000.tar is stale: written with other info_sha256"):
        write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 4})
    with pytest.raises(ExportMismatchError, match=r"image_format"):
        write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 3}, image_format="png")
    with pytest.raises(
        ExportMismatchError, match=r"synth-000001.tar is stale: it holds samples 4..6, this export's are 4..7"
    ):
        write_shards(frames_for(calls), out, NUM + 1, SHARD, progress=False, info={"seed": 3})
    with pytest.raises(ExportMismatchError, match=r"synth-000001.tar lies beyond this export's 1 shard"):
        write_shards(frames_for(calls), out, SHARD, SHARD, progress=False, info={"seed": 3})
    assert calls == []  # nothing was rendered for a refused export
    # overwrite: a smaller export removes the shard past its end; the index and the reader agree
    res = write_shards(frames_for(calls), out, SHARD, SHARD, progress=False, info={"seed": 3}, overwrite=True)
    assert calls == [] and res["skipped"] == [0] and res["complete"]
    assert (
        sorted(p.name for p in out.glob("*.tar")) == [shard_name(0)] and not (out / "synth-000001.index.json").exists()
    )
    assert len(list(SynthShardDataset(out))) == SHARD
    # overwrite with other settings rewrites every shard; the index records them
    res = write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 4}, overwrite=True)
    assert calls == [0, 1] and res["complete"]
    index = json.loads((out / "index.json").read_text())
    assert index["info"] == {"seed": 4} and index["num_samples_written"] == NUM
    assert index["settings"] == export_settings("jpg", 95, 8, True, {"seed": 4})
    # an index written by the settings-less format of older versions counts as another export
    per = json.loads((out / "synth-000000.index.json").read_text())
    del per["settings"]
    (out / "synth-000000.index.json").write_text(json.dumps(per))
    with pytest.raises(ExportMismatchError, match="synth-000000.tar is stale"):
        write_shards(frames_for(calls), out, NUM, SHARD, progress=False, info={"seed": 4})
    assert not rebuild_index(out, NUM, SHARD, settings=export_settings("jpg", 95, 8, True, {"seed": 4}))["complete"]


def test_ranks_round_robin(tmp_path):
    out = tmp_path / "r"
    c0: list = []
    c1: list = []
    r0 = write_shards(frames_for(c0), out, NUM, SHARD, rank=0, world_size=2, progress=False)
    assert c0 == [0] and not r0["complete"]
    r1 = write_shards(frames_for(c1), out, NUM, SHARD, rank=1, world_size=2, progress=False)
    assert c1 == [1] and r1["complete"]


def test_arctic_samples_and_workers(export_dir):
    ds = SynthShardDataset(export_dir, arctic_samples=True, seed=5)
    samples = list(ds)
    assert len(samples) == NUM
    for i, (inputs, targets, meta) in enumerate(samples):
        f = make_frame(i)
        # the frame's extra targets (interaction field) follow ARCTIC's, as in the live loader
        assert tuple(targets) == SAMPLE_TARGET_KEYS + tuple(f.extra_targets) and tuple(meta) == SAMPLE_META_KEYS
        assert inputs["img"].shape == (3, 224, 224) and inputs["img"].dtype == torch.float32
        aug = sample_aug_params(np.random.default_rng([5, 0, i, 3]), True, False)
        ref_in, ref_t, ref_m = frame_to_sample(f, aug)  # the live loader's path (blur scaled to the frame)
        for k in tuple(ref_t):
            a, b = targets[k], ref_t[k]
            if isinstance(a, torch.Tensor):
                assert a.dtype == b.dtype and torch.equal(a, b), k
            elif isinstance(a, np.ndarray):
                assert a.dtype == b.dtype and np.array_equal(a, b), k
            else:
                assert type(a) is type(b) and a == b, k
        assert meta["imgname"] == ref_m["imgname"] and meta["rot_angle"] == ref_m["rot_angle"]
        assert (inputs["img"] - ref_in["img"]).abs().mean() < 0.05  # JPEG only
    # the crop's box spans far fewer pixels than in ARCTIC's 1000-px crops: ARCTIC's source
    # blur is scaled down, exactly as live (a textured image, where blur shows)
    f = make_frame(1)
    f.image = np.random.default_rng(0).integers(0, 256, f.image.shape, dtype=np.uint8)
    assert source_scale(f) < 0.1
    aug = sample_aug_params(np.random.default_rng([5, 0, 1, 3]), True, False)
    got, live = frame_to_arctic_sample(f, 1, seed=5), frame_to_sample(f, aug)
    assert torch.equal(got[0]["img"], live[0]["img"]) and torch.equal(
        got[1]["mano.j2d.norm.r"], live[1]["mano.j2d.norm.r"]
    )
    plain = make_arctic_sample(
        f.image, f.bbox, f.K_full, f.image_size, f.right, f.left, f.obj, False, None, aug, f.imgname
    )[0]  # ARCTIC's full-size blur on the small crop
    assert not torch.allclose(plain["img"], live[0]["img"], atol=0.05)
    # two DataLoader workers, default collate: same samples, each exactly once
    loader = DataLoader(SynthShardDataset(export_dir, arctic_samples=True, seed=5), batch_size=None, num_workers=2)
    got = {m["imgname"]: t["mano.j2d.norm.r"] for _, t, m in loader}
    assert len(got) == NUM
    for _, t, m in samples:
        assert torch.equal(got[m["imgname"]], t["mano.j2d.norm.r"])
    # default seed/epoch: the frame's own (meta["seed"] = 3), the live loader's stream
    _, t3, _ = next(iter(SynthShardDataset(export_dir, arctic_samples=True)))
    f0 = make_frame(0)
    aug = sample_aug_params(np.random.default_rng([3, 0, 0, 3]), True, False)
    ref = make_arctic_sample(
        f0.image, f0.bbox, f0.K_full, f0.image_size, f0.right, f0.left, f0.obj, False, None, aug, f0.imgname
    )[1]
    assert torch.equal(t3["mano.j2d.norm.r"], ref["mano.j2d.norm.r"]) and t3["object.rot"].equal(ref["object.rot"])
    # default collate (the test frames alternate with and without interaction-field targets)
    plain = [smp for smp in SynthShardDataset(export_dir, arctic_samples=True) if "dist.ro" not in smp[1]]
    batch = next(iter(DataLoader(plain, batch_size=3)))
    assert batch[0]["img"].shape == (3, 3, 224, 224) and batch[1]["joints_valid_r"].dtype == torch.float64


def test_map_style_samples_equal_the_stream(export_dir, tmp_path):
    """SynthShardSamples gives, for each stored frame, the sample the streaming reader gives
    (same augmentation draw from the global index), in any access order; epochs re-augment."""
    stream = {m["imgname"]: (i, t) for i, t, m in SynthShardDataset(export_dir, arctic_samples=True, seed=5)}
    ds = SynthShardSamples(export_dir, seed=5)
    assert len(ds) == NUM
    seen = set()
    for k in reversed(range(len(ds))):
        inputs, targets, meta = ds[k]
        ref_in, ref_t = stream[meta["imgname"]]
        assert torch.equal(inputs["img"], ref_in["img"]) and torch.equal(
            targets["mano.j2d.norm.r"], ref_t["mano.j2d.norm.r"]
        )
        seen.add(meta["imgname"])
    assert len(seen) == NUM
    ds.set_epoch(1)
    assert not torch.equal(ds[0][1]["mano.j2d.norm.r"], SynthShardSamples(export_dir, seed=5)[0][1]["mano.j2d.norm.r"])
    shuffled = DataLoader(ds, batch_size=None, shuffle=True, generator=torch.Generator().manual_seed(0))
    assert sorted(m["imgname"] for _, _, m in shuffled) == sorted(seen)
    (tmp_path / "empty").mkdir()
    with tarfile.open(tmp_path / "empty" / "x.tar", "w"):
        pass
    with pytest.raises(AssetError, match="no samples"):
        SynthShardSamples(tmp_path / "empty")


def test_map_style_samples_hold_an_index_not_the_shards(export_dir, tmp_path):
    """Each rank and worker holds where the members are, not their bytes; a shard changed
    afterwards is refused on access, naming it; a worker reads through its own files."""
    ds = SynthShardSamples(export_dir, seed=5)
    held = sum(len(v) for *_, files in ds._items for v in files.values() if isinstance(v, bytes))
    assert held == 0
    ref = ds[3][0]["img"]
    workers = DataLoader(ds, batch_size=None, num_workers=2)
    assert torch.equal([x for x in workers][3][0]["img"], ref)
    copy = tmp_path / "copy"
    shutil.copytree(export_dir, copy)
    ds = SynthShardSamples(copy, seed=5)
    shard = ds._items[0][0]
    offset, size, _ = ds._items[0][3]["json"]
    raw = bytearray(shard.read_bytes())
    raw[offset] ^= 0xFF
    shard.write_bytes(bytes(raw))
    with pytest.raises(AssetError, match=f"{shard.name}.*changed since the dataset was made"):
        ds[0]


def test_reader_sharding_and_errors(export_dir, tmp_path):
    a = [f.imgname for f in SynthShardDataset(export_dir, rank=0, world_size=2)]
    b = [f.imgname for f in SynthShardDataset(export_dir, rank=1, world_size=2)]
    assert len(a) == 4 and len(b) == 3 and not set(a) & set(b)
    c = [f.imgname for r in range(3) for f in SynthShardDataset(export_dir, rank=r, world_size=3)]
    assert sorted(c) == sorted(a + b)
    with pytest.raises(AssetError, match="missing"):
        SynthShardDataset(tmp_path / "nope.tar")
    with pytest.raises(AssetError, match="no .tar shards"):
        SynthShardDataset(tmp_path)
    bad = tmp_path / "bad.tar"
    bad.write_bytes(b"garbage" * 100)
    with pytest.raises(AssetError, match="bad.tar"):
        list(SynthShardDataset(bad))


def test_gaps_from_dropped_samples_and_dataset_adapter(tmp_path):
    from hogsa_loader.sample.export import dataset_frames_for_shard

    class FakeHogsa:  # HOGSADataset's frames(g) / batch_size interface
        batch_size = 3

        def __init__(self):
            self.calls = []

        def frames(self, g):
            self.calls.append(g)
            out = []
            for i in range(g * 3, g * 3 + 3):
                out.append(None if i % 5 == 2 else make_frame(i))  # 2, 7 dropped
            return out

    ds = FakeHogsa()
    out = tmp_path / "gaps"
    res = write_shards(dataset_frames_for_shard(ds, NUM, SHARD), out, NUM, SHARD, progress=False)
    assert res["samples"] == NUM - 1 and res["complete"]
    per = json.loads((out / "synth-000000.index.json").read_text())
    assert per["keys"] == ["0000000000", "0000000001", "0000000003"] and per["expected"] == 4
    assert "dropped" not in per  # (a dataset without statistics: the count only)
    index = json.loads((out / "index.json").read_text())
    assert index["num_dropped"] == 1 and index["dropped"] is None
    back = list(SynthShardDataset(out))
    assert [f.meta["index"] for f in back] == [0, 1, 3, 4, 5, 6]
    for f in back:
        assert_same_frame(make_frame(f.meta["index"]), f)

    def wrong(shard):
        yield make_frame(5)  # belongs to shard 1

    with pytest.raises(ValueError, match="outside"):
        write_shards(wrong, tmp_path / "w", NUM, SHARD, progress=False)


def test_shard_drops_by_reason_survive_a_resumed_export(tmp_path):
    """Each shard's index file keeps the reasons its samples were dropped for, so the export's
    ``index.json`` sums them over all shards, also those written by an earlier, interrupted pass;
    reasons that do not explain a shard's gaps are not kept."""
    import types

    from hogsa_loader.sample.export import dataset_frames_for_shard

    reasons = {1: "nan", 4: "out_of_crop", 5: "out_of_crop"}  # none in shard 2 (samples 8, 9)

    class Counting:  # HOGSADataset's frames(g) / batch_size / total_stats interface
        batch_size = 2

        def __init__(self):
            self.dropped = {"nan": 0, "out_of_crop": 0}
            self.drawn = []

        def frames(self, g):
            self.drawn.append(g)
            out = []
            for i in (2 * g, 2 * g + 1):
                if i in reasons:
                    self.dropped[reasons[i]] += 1
                out.append(None if i in reasons else make_frame(i))
            return out

        def total_stats(self):
            return types.SimpleNamespace(dropped=dict(self.dropped))

    out = tmp_path / "resumed"
    first = Counting()

    def interrupted(shard):
        if shard == 1:
            raise RuntimeError("interrupted")
        return dataset_frames_for_shard(first, 10, 4)(shard)

    with pytest.raises(RuntimeError):
        write_shards(interrupted, out, 10, 4, progress=False)
    index = json.loads((out / "index.json").read_text())
    assert not index["complete"] and index["dropped"] == {"nan": 1} and index["num_dropped"] == 1
    second = Counting()  # the resumed pass: a fresh dataset draws shards 1 and 2 only
    res = write_shards(dataset_frames_for_shard(second, 10, 4), out, 10, 4, progress=False)
    assert res["skipped"] == [0] and second.drawn == [2, 3, 4]
    per = json.loads((out / "synth-000001.index.json").read_text())
    assert per["dropped"] == {"out_of_crop": 2} and per["count"] == 2
    assert json.loads((out / "synth-000002.index.json").read_text())["dropped"] == {}
    index = json.loads((out / "index.json").read_text())
    assert index["complete"] and index["num_samples_written"] == 7 and index["num_dropped"] == 3
    assert index["dropped"] == {"nan": 1, "out_of_crop": 2}
    assert (res["num_samples_written"], res["num_dropped"], res["dropped"]) == (7, 3, index["dropped"])
    assert [s.get("dropped") for s in index["shards"]] == [{"nan": 1}, {"out_of_crop": 2}, {}]

    # a shard without reasons (or with a bad record) leaves the sum unknown, not short
    path = out / "synth-000000.index.json"
    rec = json.loads(path.read_text())
    for bad in (None, {"nan": "one"}, [1], {"nan": 2}, {"nan": 2, "out_of_crop": -1}):  # (shard 0 lacks 1 sample)
        rec["dropped"] = bad
        path.write_text(json.dumps(rec))
        index = rebuild_index(out, 10, 4, settings=index["settings"])
        assert index["dropped"] is None and index["num_dropped"] == 3 and "dropped" not in index["shards"][0]

    # reasons that do not add up to the gaps (a render batch reaching into the next shard) are left out
    third = Counting()
    straddle = tmp_path / "straddle"
    write_shards(dataset_frames_for_shard(third, 10, 5), straddle, 10, 5, progress=False)
    kept = [json.loads((straddle / f"synth-00000{k}.index.json").read_text()) for k in range(2)]
    assert [k["count"] for k in kept] == [3, 4] and third.drawn == [0, 1, 2, 2, 3, 4]  # batch 2: samples 4, 5
    assert [k.get("dropped") for k in kept] == [None, None]
    index = json.loads((straddle / "index.json").read_text())
    assert index["dropped"] is None and index["num_dropped"] == 3


def test_cli_export_takes_its_rank_from_torchrun_or_srun(tmp_path, monkeypatch, capsys):
    """``hogsa export`` wiring (rank/world from the environment, resume) on a stand-in dataset."""
    import types

    from hogsa_loader.cli import commands as cli_main
    from hogsa_loader.cli.main import main
    from hogsa_loader.sample.config import export_info

    made = []

    class StandIn:
        def __init__(self, bundle, data, config):
            self.batch_size = config.run.batch_size
            self.render_size = 48
            self.kw = {
                **export_info(config),
                "num_samples": config.run.num_samples,
                "exclude_person": config.backgrounds.exclude_person,
                "srm_tta": config.refinement.srm_tta,
            }
            self.stats = types.SimpleNamespace(as_dict=lambda: {"num_dropped": 0})
            made.append(self)

        def frames(self, g):
            return [make_frame(i) for i in range(g * self.batch_size, (g + 1) * self.batch_size)]

    monkeypatch.setattr(cli_main, "HOGSADataset", StandIn)
    out = tmp_path / "cli"
    (tmp_path / "B").mkdir()  # (folders, as the command checks before any work)
    (tmp_path / "D").mkdir()
    args = [
        "export",
        "--bundle",
        str(tmp_path / "B"),
        "--data",
        str(tmp_path / "D"),
        "--out",
        str(out),
        "--num",
        "7",
        "--shard-size",
        "2",
        "--batch-size",
        "2",
        "--seed",
        "4",
        "--quiet",
    ]
    for rank in (1, 0):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        assert main(args) == 0
    assert made[0].kw["seed"] == 4 and made[0].kw["num_samples"] == 7 and made[0].kw["interfield"] is False
    index = json.loads((out / "index.json").read_text())
    assert index["complete"] and index["num_samples_written"] == 7 and index["info"]["seed"] == 4
    assert json.loads((out / "synth-000001.index.json").read_text())["rank"] == 1
    assert len(list(SynthShardDataset(out))) == 7
    # srun's two tasks: the ranks from SLURM_PROCID / SLURM_STEP_NUM_TASKS, no flag
    monkeypatch.delenv("RANK")
    monkeypatch.delenv("WORLD_SIZE")
    srun = list(args)
    srun[srun.index("--out") + 1] = str(tmp_path / "srun")
    for rank in (1, 0):
        monkeypatch.setenv("SLURM_PROCID", str(rank))
        monkeypatch.setenv("SLURM_STEP_NUM_TASKS", "2")
        assert main(srun) == 0
    assert json.loads((tmp_path / "srun" / "synth-000001.index.json").read_text())["rank"] == 1
    assert json.loads((tmp_path / "srun" / "index.json").read_text())["num_samples_written"] == 7
    monkeypatch.delenv("SLURM_PROCID")
    monkeypatch.delenv("SLURM_STEP_NUM_TASKS")
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main(args[:-1] + ["--out", str(tmp_path / "if"), "--interfield", "--quiet"]) == 0
    assert made[-1].kw["interfield"] is True
    assert made[0].kw["exclude_person"] is False and made[0].kw["srm_tta"] == 1
    assert index["info"]["exclude_person"] is False and index["info"]["srm_tta"] == 1  # every setting recorded
    assert (
        main(args[:-1] + ["--out", str(tmp_path / "ep"), "--exclude-person", "--srm", "--srm-tta", "8", "--quiet"]) == 0
    )
    assert made[-1].kw["exclude_person"] is True and made[-1].kw["srm_tta"] == 8
    info = json.loads((tmp_path / "ep" / "index.json").read_text())["info"]
    assert info["exclude_person"] is True and info["srm_tta"] == 8
    # bad numbers are refused before the dataset is built; another export's folder is refused
    n_made = len(made)
    for flag in ("--num", "--shard-size", "--batch-size"):
        bad = list(args)
        bad[bad.index(flag) + 1] = "0"
        assert main(bad) == 2
    assert len(made) == n_made
    other = list(args)
    other[other.index("--seed") + 1] = "5"
    assert main(other) == 2
    assert main(other + ["--overwrite"]) == 0 and main(other) == 0
    # an export whose every sample is dropped fails (exit 1) and says so
    monkeypatch.setattr(StandIn, "frames", lambda self, g: [None] * self.batch_size)
    empty = list(args)
    empty[empty.index("--out") + 1] = str(tmp_path / "empty")
    monkeypatch.delenv("RANK")
    monkeypatch.delenv("WORLD_SIZE")
    capsys.readouterr()
    assert main(empty) == 1
    assert "the export kept no sample" in capsys.readouterr().err


def test_failed_export_leaves_nothing_behind(tmp_path):
    def failing(shard):
        yield make_frame(0)
        raise RuntimeError("render failed")

    out = tmp_path / "new"
    with pytest.raises(RuntimeError, match="render failed"):
        write_shards(failing, out, NUM, SHARD, progress=False)
    assert not out.exists()  # a folder the export created is removed again
    given = tmp_path / "given"
    given.mkdir()
    with pytest.raises(RuntimeError, match="render failed"):
        write_shards(failing, given, NUM, SHARD, progress=False)
    assert list(given.iterdir()) == []  # no index.json, no temporary shard, no lock file


def test_readers_follow_index_json(tmp_path, export_dir):
    out = tmp_path / "e"
    write_shards(frames_for([]), out, NUM, SHARD, progress=False, info={"seed": 3}, rank=0, world_size=2)
    assert not json.loads((out / "index.json").read_text())["complete"]  # rank 1's shard is missing
    for reader in (SynthShardDataset, SynthShardSamples):
        with pytest.raises(AssetError, match="export is incomplete: 1 of 2 shards"):
            reader(out)
    assert [f.imgname for f in SynthShardDataset(out, incomplete=True)] == [make_frame(i).imgname for i in range(SHARD)]
    assert len(SynthShardSamples(out, incomplete=True)) == SHARD
    # a stray .tar in a complete export's folder is not read
    full = tmp_path / "full"
    shutil.copytree(export_dir, full)
    shutil.copy(full / shard_name(0), full / "stray.tar")
    assert len(list(SynthShardDataset(full))) == NUM and len(SynthShardSamples(full)) == NUM
    # a shard the index lists but that is missing or resized
    (full / shard_name(1)).unlink()
    with pytest.raises(AssetError, match="missing"):
        SynthShardDataset(full)


def test_member_checksums_catch_flipped_bytes(tmp_path, export_dir):
    out = tmp_path / "e"
    shutil.copytree(export_dir, out)
    rec = json.loads((out / "synth-000000.index.json").read_text())
    assert set(rec["members_sha256"]) >= {"0000000000.jpg", "0000000000.json"}
    with tarfile.open(out / shard_name(0)) as tar:
        member = tar.getmember("0000000001.jpg")
    blob = bytearray((out / shard_name(0)).read_bytes())
    blob[member.offset_data + member.size // 2] ^= 0x55  # a flipped byte inside the JPEG
    (out / shard_name(0)).write_bytes(bytes(blob))
    with pytest.raises(AssetError, match=r"0000000001\.jpg: sha256 does not match"):
        list(SynthShardDataset(out))
    with pytest.raises(AssetError, match=r"0000000001\.jpg: sha256 does not match"):
        SynthShardSamples(out)
    # a shard index without checksums is refused, not read unchecked
    del rec["members_sha256"]
    (out / "synth-000000.index.json").write_text(json.dumps(rec))
    with pytest.raises(AssetError, match="records no members_sha256"):
        list(SynthShardDataset(out))


def test_a_shard_of_the_right_size_but_other_bytes_is_rewritten(tmp_path):
    """Completeness is judged by the shard's sha256, not its size: tar pads to 10,240-byte
    records, so a torn or foreign shard can have exactly the recorded size."""
    out = tmp_path / "e"
    calls: list = []
    write_shards(frames_for(calls), out, NUM, SHARD, progress=False)
    tar = out / shard_name(0)
    good = tar.read_bytes()
    torn = bytearray(good)
    torn[len(torn) // 2] ^= 0xFF  # same size, other bytes
    tar.write_bytes(bytes(torn))
    calls.clear()
    res = write_shards(frames_for(calls), out, NUM, SHARD, progress=False)
    assert calls == [0] and res["written"] == [0] and res["skipped"] == [1]
    assert tar.read_bytes() == good
    rec = json.loads((out / "synth-000000.index.json").read_text())
    assert rec["sha256"] == hashlib.sha256(good).hexdigest()


def _members(frame_index: int = 0) -> dict[str, bytes]:
    """``{extension: bytes}`` of a stored sample (what the readers pass to ``decode_frame``)."""
    return {split_member_name(k)[1]: v for k, v in encode_frame(make_frame(frame_index), "s/0").items()}


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def test_crafted_sample_members_are_refused_before_they_are_decoded(tmp_path):
    """Decompression bombs (an alpha larger than its image, labels that inflate to megabytes, a
    tar member announcing gigabytes) and malformed records give the readers' typed errors,
    naming the member; a frame with labels that are not finite is not decoded."""
    good = _members()
    labels = dict(np.load(io.BytesIO(good["labels.npz"]), allow_pickle=False))
    cases = {
        "alpha.png": (_png_of(np.zeros((S + 1, S), np.uint8)), "announces 48x49 pixels, more than 2304"),
        "labels.npz": (_npz(bomb=np.zeros(2**21, np.float32), **labels), "uncompressed, more than labels hold"),
    }
    for member, (data, message) in cases.items():
        with pytest.raises((ValueError, AssetError), match=message):
            decode_frame({**good, member: data}, "s/0")
    nan = {**labels, "right.j2d": np.full_like(labels["right.j2d"], np.nan)}
    with pytest.raises(ValueError, match="not finite: right.j2d"):
        decode_frame({**good, "labels.npz": _npz(**nan)}, "s/0")
    missing = {k: v for k, v in labels.items() if k != "obj.radian"}
    with pytest.raises(ValueError, match=r"s/0: malformed sample \(KeyError"):
        decode_frame({**good, "labels.npz": _npz(**missing)}, "s/0")
    with pytest.raises(ValueError, match=r"malformed sample \(TypeError"):
        decode_frame({**good, "json": b"[]"}, "s/0")
    # a tar member that announces 3 GiB (a sparse member: the file itself is small)
    head = tarfile.TarInfo("s/0.jpg")
    head.size = 3 * 2**30
    (tmp_path / "bomb.tar").write_bytes(head.tobuf(format=tarfile.GNU_FORMAT))
    with pytest.raises(AssetError, match=r"member s/0.jpg: 3221225472 bytes, more than a sample member's"):
        list(iter_tar_samples(tmp_path / "bomb.tar"))


def _png_of(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()
