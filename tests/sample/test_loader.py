"""The synthetic loader: bundle validation, HOGSADataset samples, mixing, determinism."""

from __future__ import annotations

import hashlib
import itertools
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import tiny_srm, write_coco
from torch.utils.data import DataLoader, default_collate

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.protocol import HeldOutWarning
from hogsa_loader.compose import ProceduralBackgrounds
from hogsa_loader.errors import AssetError, UsageError
from hogsa_loader.models.bundle import load_bundle, write_bundle
from hogsa_loader.sample import (
    CameraConfig,
    HOGSADataset,
    LoaderConfig,
    MixedLoader,
    SampleChecks,
    is_synthetic,
    num_synthetic,
    parse_synthetic_imgname,
    with_options,
)
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig, patch_warp_matrix, unnormalize_kp2d
from hogsa_loader.sample.cameras import NOVEL_VIEW
from hogsa_loader.sample.config import export_info
from hogsa_loader.sample.mixing import added_synthetic
from hogsa_loader.sample.synth import joints_on_alpha, source_scale

#: Small patches keep rendering cheap; real and synthetic samples use the same config.
CFG = ArcticConfig(img_res=64)


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """One intra-op thread: rendering many small images does not gain from more, and a
    shared 2-core machine slows down badly when threads spin against each other."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def bundle_dir(untrained_bundle) -> Path:
    return untrained_bundle


def _config(**kw) -> LoaderConfig:
    """The tests' loader config: ``CFG`` samples and the options ``kw`` by name."""
    return with_options(LoaderConfig(), arctic=CFG, **kw)


def _dataset(bundle_dir, world, *, backgrounds=None, poses=None, **kw) -> HOGSADataset:
    kw.setdefault("batch_size", 4)
    kw.setdefault("num_samples", 4)
    if isinstance(poses, str):  # a registered name: a config setting; else a pose-source object
        kw["poses"], poses = poses, None
    return HOGSADataset(
        bundle_dir,
        world,
        _config(**kw),
        poses=poses,
        backgrounds=backgrounds if backgrounds is not None else ProceduralBackgrounds(),
    )


@pytest.fixture(scope="module")
def frames(bundle_dir, tiny_world):
    """(dataset, kept frames of two render batches)."""
    ds = _dataset(bundle_dir, tiny_world, num_samples=16, batch_size=8, seed=3)
    out = [f for g in range(2) for f in ds.frames(g) if f is not None]
    return ds, out


def _describe(x):
    if isinstance(x, torch.Tensor):
        return ("tensor", tuple(x.shape), x.dtype)
    if isinstance(x, np.ndarray):
        return ("ndarray", x.shape, x.dtype)
    return (type(x).__name__,)


def test_synthetic_sample_matches_real(frames, tiny_world):
    ds, fr = frames
    syn = ds.to_sample(fr[0])
    real = ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0)[0]
    for s, r in zip(syn, real):
        assert list(s) == list(r)  # same keys, same order
        for k in r:
            assert _describe(s[k]) == _describe(r[k]), k
    assert is_synthetic(syn[2]["imgname"]) and not is_synthetic(real[2]["imgname"])
    info = parse_synthetic_imgname(syn[2]["imgname"])
    assert info["seed"] == 3 and info["index"] == fr[0].meta["index"] and info["object"] == "box"
    # collated together exactly like real samples
    batch = default_collate([real, syn])
    assert batch[2]["imgname"][1] == syn[2]["imgname"]
    assert torch.isfinite(syn[0]["img"]).all()
    # the source blur is scaled against this world's cropped images (256 px here, ARCTIC's 1000)
    wm = ArcticRoot(tiny_world).world_meta()
    assert wm.cropped_size != 1000 and fr[0].meta["cropped_size"] == wm.cropped_size
    assert source_scale(fr[0]) == pytest.approx(fr[0].bbox[2] * 200 * 1.5 / wm.cropped_size)


def test_keypoints_lie_on_rendered_alpha(frames):
    ds, fr = frames
    assert len(fr) >= 8
    assert ds._pipe.last_backend == "torch"  # what backend="auto" resolved to on the CPU
    crop_hits, own_hits, patch_hits, swapped_hits = [], [], [], []
    shifted_hits: dict[tuple[int, int], list] = {}
    for f in fr:
        _, targets, _ = ds.to_sample(f)
        for h, side, part in ((f.right, "r", 0), (f.left, "l", 1)):
            if not h.valid:
                continue
            S = f.alpha.shape[0]
            inside = (h.j2d >= 0).all(1) & (h.j2d <= S - 1).all(1)
            crop_hits.extend(joints_on_alpha(h.j2d[inside], f.alpha, radius=0))
            # each hand's joints on that hand's own opacity or the object's (which hides fingers
            # behind it), nearest pixel; controls: the other hand's labels, and labels moved 2 px
            own = np.maximum(f.part_alpha[..., part], f.part_alpha[..., 2])
            own_hits.extend(joints_on_alpha(h.j2d[inside], own, radius=0))
            wrong = np.maximum(f.part_alpha[..., 1 - part], f.part_alpha[..., 2])
            swapped_hits.extend(joints_on_alpha(h.j2d[inside], wrong, radius=0))
            for d in ((2, 0), (-2, 0), (0, 2), (0, -2)):
                moved = h.j2d[inside] + np.array(d, dtype=np.float64)
                shifted_hits.setdefault(d, []).extend(joints_on_alpha(moved, own, radius=0))
            # the same check after ARCTIC's augmentation, in the 64-px patch
            aug = ds.aug_params(f.meta["index"])
            crop_dim = int(aug.sc * f.bbox[2] * 200)
            M = patch_warp_matrix(f.bbox[:2], crop_dim, aug.rot, CFG.img_res)
            a = cv2.warpAffine(f.alpha, M, (CFG.img_res, CFG.img_res), flags=cv2.INTER_LINEAR)
            px = unnormalize_kp2d(targets[f"mano.j2d.norm.{side}"].numpy(), CFG.img_res)
            ok = (px >= 0).all(1) & (px <= CFG.img_res - 1).all(1)
            # labels are truncated the HMR way (up to 1 px right/below): look 1 px around
            patch_hits.extend(joints_on_alpha(px[ok], a, radius=1))
    crop_rate, patch_rate = float(np.mean(crop_hits)), float(np.mean(patch_hits))
    own_rate, swapped_rate = float(np.mean(own_hits)), float(np.mean(swapped_hits))
    shifted = {d: float(np.mean(v)) for d, v in shifted_hits.items()}
    print(
        f"joints on alpha: crop {crop_rate:.4f} ({len(crop_hits)} joints), patch {patch_rate:.4f} "
        f"({len(patch_hits)}); own hand or object {own_rate:.4f}, left/right swapped {swapped_rate:.4f}, "
        f"moved 2 px {shifted}"
    )
    assert len(crop_hits) >= 200
    assert crop_rate >= 0.99
    assert patch_rate >= 0.99
    # the rest are joints behind the other hand (about as many as the other hand's alpha holds)
    assert own_rate >= 0.92
    assert swapped_rate <= 0.75  # labels of the wrong hand fail the bound above by far
    assert max(shifted.values()) < own_rate  # the labels sit where the hand is, not 2 px beside it


def test_mixed_loader_exact_ratio(bundle_dir, tiny_world):
    real_ds = ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0)
    real = DataLoader(real_ds, batch_size=5, shuffle=False)
    syn = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=4, seed=1)
    mixed = MixedLoader(real, syn, ratio=0.5)
    assert num_synthetic(0.5, 5) == 3
    ref = next(iter(real))
    batches = list(itertools.islice(iter(mixed), 3))
    for b in batches:
        names = b[2]["imgname"]
        assert len(names) == 5
        assert sum(is_synthetic(n) for n in names) == 3
        assert [is_synthetic(n) for n in names] == [False, False, True, True, True]
        for part_b, part_r in zip(b, ref):
            assert list(part_b) == list(part_r)
            for k in part_r:
                assert _describe(part_b[k])[0] == _describe(part_r[k])[0], k
                if isinstance(part_r[k], torch.Tensor):
                    assert part_b[k].shape == part_r[k].shape and part_b[k].dtype == part_r[k].dtype, k
    # real samples are consumed in order, none skipped
    reals = [n for b in batches for n in b[2]["imgname"] if not is_synthetic(n)]
    assert reals == [real_ds[i][2]["imgname"] for i in range(6)]


class _Indexed(torch.utils.data.Dataset):
    """Real stand-in: sample i is {"x": i}."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        return {"x": torch.tensor(i)}


@pytest.mark.parametrize(
    "n, B, ratio, real_kw, drop_last",
    [
        (100, 10, 0.5, {"sampler": "distributed"}, True),  # one of two ranks: half the samples
        (105, 10, 0.5, {"drop_last": True}, True),  # the real loader drops its last 5
        (41, 40, 0.95, {}, False),  # a high ratio: the last real sample still gets its (smaller) batch
        (23, 8, 0.25, {}, False),
    ],
)
def test_mixed_loader_length_matches_what_it_yields(n, B, ratio, real_kw, drop_last):
    from torch.utils.data.distributed import DistributedSampler

    ds = _Indexed(n)
    if real_kw.get("sampler") == "distributed":
        real_kw = {"sampler": DistributedSampler(ds, num_replicas=2, rank=0, shuffle=False)}
    real = DataLoader(ds, batch_size=B, **real_kw)
    mixed = MixedLoader(real, itertools.repeat({"x": torch.tensor(-1)}), ratio=ratio, drop_last=drop_last)
    batches = list(mixed)
    assert len(mixed) == len(batches)
    if "sampler" not in real_kw:  # a sized iterable real dataset (its sampler has no length): same count
        it_ds = type(
            "SizedIterable",
            (torch.utils.data.IterableDataset,),
            {"__iter__": lambda self: (ds[i] for i in range(n)), "__len__": lambda self: n},
        )()
        it_real = DataLoader(it_ds, batch_size=B, drop_last=bool(real_kw.get("drop_last")))
        it_mixed = MixedLoader(it_real, itertools.repeat({"x": torch.tensor(-1)}), ratio=ratio, drop_last=drop_last)
        assert len(it_mixed) == len(list(it_mixed)) == len(batches)
    seen = [int(v) for b in batches for v in b["x"] if v >= 0]
    expected = [int(v) for b in real for v in b["x"]]
    assert seen == (expected if not drop_last else expected[: len(seen)])  # in order, none skipped or repeated
    if not drop_last:
        assert seen == expected  # every real sample of the pass is used
    for b in batches:
        k = len(b["x"])
        assert k <= B and int((b["x"] < 0).sum()) == num_synthetic(ratio, k)


@pytest.mark.parametrize(
    "n, B, ratio, drop_last", [(23, 8, 0.5, False), (23, 8, 0.25, True), (35, 6, 0.6, False), (9, 4, 0.0, False)]
)
def test_mixed_loader_add_mode_keeps_the_real_batches(n, B, ratio, drop_last):
    ds = _Indexed(n)
    real = DataLoader(ds, batch_size=B, drop_last=drop_last)
    # MixedLoader's own drop_last is for "replace"; the real loader's decides here
    mixed = MixedLoader(
        real, itertools.repeat({"x": torch.tensor(-1)}), ratio=ratio, mode="add", drop_last=not drop_last
    )
    batches = list(mixed)
    assert len(mixed) == len(batches) == len(real)
    assert mixed.batch_size == B + added_synthetic(ratio, B)
    for b, r in zip(batches, real, strict=True):
        k = len(r["x"])
        assert torch.equal(b["x"][:k], r["x"])  # the real batch, whole and first
        n_syn = int((b["x"] < 0).sum())
        assert n_syn == added_synthetic(ratio, k) == len(b["x"]) - k
        assert abs(n_syn / len(b["x"]) - ratio) <= 0.5 / len(b["x"]) + 1e-9
    assert added_synthetic(0.5, 32) == 32 and added_synthetic(0.25, 30) == 10
    assert [added_synthetic(0.6, b) for b in (1, 3, 5)] == [2, 5, 8]  # exact halves round up
    with pytest.raises(ValueError, match="single samples"):
        MixedLoader(DataLoader(ds, batch_size=None), [], ratio=0.5)
    with pytest.raises(ValueError, match="ratio < 1"):
        MixedLoader(real, [], ratio=1.0, mode="add")
    with pytest.raises(ValueError, match="mode"):
        MixedLoader(real, [], ratio=0.5, mode="append")


def test_same_seed_same_samples_with_two_workers(bundle_dir, tiny_world):
    def run():
        ds = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=2, seed=7)
        dl = DataLoader(ds, batch_size=None, num_workers=2)
        return [(s[2]["imgname"], s[0]["img"]) for s in dl]

    a, b = run(), run()
    assert len(a) >= 4
    assert [n for n, _ in a] == [n for n, _ in b]
    assert all(torch.equal(x, y) for (_, x), (_, y) in zip(a, b))
    # every index appears once; a sample regenerates alone from (seed, index)
    idx = [parse_synthetic_imgname(n)["index"] for n, _ in a]
    assert len(set(idx)) == len(idx)
    one = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=2, seed=7).sample(idx[-1])
    assert one is not None and torch.allclose(one[0]["img"], a[-1][1], atol=1e-4)


def test_batches_are_balanced_over_the_models(bundle_dir, tiny_world):
    ds = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=2, seed=3)
    ds.keys = [("s01", "box"), ("s01", "laptop"), ("s02", "notebook")]  # only batch_key reads them here
    for epoch in (0, 1):
        keys = [ds.batch_key(g, epoch) for g in range(60)]
        for block in range(20):  # each block of len(keys) batches uses every model once
            assert sorted(keys[3 * block : 3 * block + 3]) == sorted(ds.keys)
        orders = {tuple(keys[3 * b : 3 * b + 3]) for b in range(20)}
        assert len(orders) > 1  # the order within a block is drawn, not fixed
    assert [ds.batch_key(g, 0) for g in range(60)] != [ds.batch_key(g, 1) for g in range(60)]
    same = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=2, seed=3)
    other = _dataset(bundle_dir, tiny_world, num_samples=8, batch_size=2, seed=4)
    for d in (same, other):
        d.keys = list(ds.keys)
    assert [same.batch_key(g, 0) for g in range(30)] == [ds.batch_key(g, 0) for g in range(30)]  # a pure function
    assert [other.batch_key(g, 0) for g in range(30)] != [ds.batch_key(g, 0) for g in range(30)]  # of the seed


def test_set_epoch_reaches_persistent_workers_and_waits_for_the_next_iteration(bundle_dir, tiny_world):
    ds = _dataset(bundle_dir, tiny_world, num_samples=4, batch_size=2, seed=5)
    dl = DataLoader(ds, batch_size=None, num_workers=1, persistent_workers=True)
    per_epoch = {}
    for epoch in (0, 1, 0):
        ds.set_epoch(epoch)
        per_epoch.setdefault(epoch, []).append([(s[2]["imgname"], s[0]["img"]) for s in dl])
    (e0, e0_again), (e1,) = per_epoch[0], per_epoch[1]
    assert e0 and e1 and all(parse_synthetic_imgname(n)["epoch"] == 0 for n, _ in e0)
    assert all(parse_synthetic_imgname(n)["epoch"] == 1 for n, _ in e1)  # the worker saw set_epoch(1)
    assert [n for n, _ in e0] == [n for n, _ in e0_again] and all(
        torch.equal(x, y) for (_, x), (_, y) in zip(e0, e0_again)
    )
    name, img = e1[-1]
    again = ds.sample(parse_synthetic_imgname(name)["index"], epoch=1)
    assert again is not None and again[2]["imgname"] == name and torch.allclose(again[0]["img"], img, atol=1e-4)
    # a deep copy has its own shared epoch (its workers see its set_epoch, not the original's)
    import copy

    twin = copy.deepcopy(ds)
    twin.set_epoch(3)
    assert ds.epoch == 0 and twin._epoch.is_shared()
    names = [s[2]["imgname"] for s in DataLoader(twin, batch_size=None, num_workers=1)]
    assert names and all(parse_synthetic_imgname(n)["epoch"] == 3 for n in names)
    # a set_epoch during an iteration leaves the rest of that iteration at its epoch
    ds = _dataset(bundle_dir, tiny_world, num_samples=4, batch_size=4, seed=5)
    it = iter(ds)
    first = next(it)
    ds.set_epoch(1)
    rest = list(it)
    assert rest and all(parse_synthetic_imgname(s[2]["imgname"])["epoch"] == 0 for s in [first, *rest])
    ref = [ds.to_sample(f) for f in ds.frames(0, epoch=0) if f is not None]  # the same render batch, epoch 0
    assert [s[2]["imgname"] for s in ref] == [s[2]["imgname"] for s in [first, *rest]]
    assert all(
        torch.equal(a[0]["img"], b[0]["img"]) for a, b in zip(ref, [first, *rest])
    )  # augmentation of epoch 0 too


def test_background_source_is_built_at_construction(bundle_dir, tiny_world, tmp_path, monkeypatch):
    """A bad COCO folder fails when the dataset is made (not later, inside workers), and
    workers receive the built source."""
    import pickle

    from hogsa_loader.compose import FolderBackgrounds

    with pytest.raises(AssetError, match="nope"):
        HOGSADataset(bundle_dir, tiny_world, _config(coco_root=tmp_path / "nope"))
    (tmp_path / "bg").mkdir()
    cv2.imwrite(str(tmp_path / "bg" / "a.png"), np.full((40, 50, 3), 90, np.uint8))
    ds = HOGSADataset(bundle_dir, tiny_world, _config(background_folder=tmp_path / "bg", num_samples=2))
    assert isinstance(ds.backgrounds, FolderBackgrounds) and ds.backgrounds.paths == [tmp_path / "bg" / "a.png"]
    assert pickle.loads(pickle.dumps(ds)).backgrounds.paths == ds.backgrounds.paths
    with pytest.raises(ValueError, match="apply to COCO images"):  # not silently ignored
        HOGSADataset(bundle_dir, tiny_world, _config(background_folder=tmp_path / "bg", exclude_person=True))
    # COCO options reach the source: people excluded, explicit image folder
    monkeypatch.setenv("HOGSA_CACHE", str(tmp_path / "cache"))  # (the COCO selection cache, not ~/.cache)
    coco = write_coco(tmp_path / "coco")
    ds = HOGSADataset(
        bundle_dir,
        tiny_world,
        _config(coco_root=coco, exclude_person=True, coco_image_dir=coco / "images" / "train2017"),
    )
    assert ds.backgrounds.exclude_person and sorted(ds.backgrounds.image_ids) == [1, 3, 5]  # (2, 4 show people)


def test_cuda_device_refused_in_workers(bundle_dir, tiny_world):
    ds = _dataset(bundle_dir, tiny_world, device="cuda")
    with pytest.raises(RuntimeError, match="must not touch CUDA"):
        next(iter(DataLoader(ds, batch_size=None, num_workers=1)))


def test_bad_bundle_lists_every_problem(bundle_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(bundle_dir, bad)
    (bad / "hogs" / "s01_box" / "hand_left" / "gaussians.safetensors").unlink()
    (bad / "srm" / "srm" / "srm.safetensors").write_bytes(b"other weights")
    man = json.loads((bad / "manifest.json").read_text())
    man["objects"]["box"]["template_hash"] = "0" * 64
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(AssetError) as err:
        load_bundle(bad)
    msg = str(err.value)
    assert "3 problems" in msg
    assert "hand_left" in msg and "gaussians.safetensors" in msg
    assert "srm.safetensors" in msg and "sha256" in msg
    assert "part object was trained on template" in msg
    with pytest.raises(AssetError, match="manifest.json is missing"):
        load_bundle(tmp_path)
    assert load_bundle(bundle_dir).keys == [("s01", "box")]


def test_a_bundle_is_replaced_only_when_the_new_one_is_whole(bundle_dir, tiny_world, tmp_path, monkeypatch):
    """A rebuild killed part-way (here: an error while copying) leaves the old bundle, loadable,
    and no partial folder; an old bundle moved aside by a killed swap is put back; a second
    writer of the same bundle is refused."""
    import hogsa_loader.models.bundle as bundle_mod
    from hogsa_loader.io.locks import FolderBusyError, writer_lock

    run = bundle_dir / "hogs" / "s01_box"
    out = tmp_path / "b"
    write_bundle(out, tiny_world, [run])
    before = (out / "manifest.json").read_bytes()

    def torn(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(bundle_mod, "_copy_run", torn)
    with pytest.raises(OSError, match="disk full"):
        write_bundle(out, tiny_world, [run])
    monkeypatch.undo()
    assert (out / "manifest.json").read_bytes() == before and load_bundle(out).keys == [("s01", "box")]
    assert not list(tmp_path.glob(".b.partial-*"))
    out.rename(tmp_path / ".b.old-x")  # killed between moving the old bundle aside and the new one in
    with writer_lock(tmp_path, ".b.bundle.lock", what="another writer"):
        with pytest.raises(FolderBusyError):
            write_bundle(out, tiny_world, [run])
    assert not out.exists()
    write_bundle(out, tiny_world, [run])
    assert load_bundle(out).keys == [("s01", "box")] and not list(tmp_path.glob(".b.old-*"))


def test_bundle_keeps_the_runs_light(bundle_dir, tiny_world, tmp_path):
    """A run trained with a learned light renders with it from the bundle too."""
    from hogsa_loader.models.gaussians.hogs_model import LIGHT_DIR
    from hogsa_loader.models.gaussians.shading import DirectionalLight, save_light

    run = tmp_path / "run"
    shutil.copytree(bundle_dir / "hogs" / "s01_box", run)
    shutil.rmtree(run / LIGHT_DIR, ignore_errors=True)
    save_light(DirectionalLight(direction=(0.3, -0.2, 1.0), ambient=0.2, diffuse=0.7), run / LIGHT_DIR)
    b = load_bundle(write_bundle(tmp_path / "b", tiny_world, [run]))
    root = ArcticRoot(tiny_world)
    model = b.load_hogs(("s01", "box"), root.mano_layers(), root.object_templates())
    assert isinstance(model.light, DirectionalLight)
    assert torch.equal(
        model.light.state_dict()["direction"], DirectionalLight(direction=(0.3, -0.2, 1.0)).state_dict()["direction"]
    )
    assert b.hogs[("s01", "box")].light is not None and b.hogs[("s01", "box")].light.keys() == {
        "tensors_sha256",
        "manifest_sha256",
    }
    # rebuilding the bundle from its own runs keeps them (and the light)
    b2 = load_bundle(write_bundle(tmp_path / "b", tiny_world, [tmp_path / "b" / "hogs" / "s01_box"]))
    assert b2.hogs[("s01", "box")].light == b.hogs[("s01", "box")].light
    # a changed light is found; a light file the manifest does not list is refused
    (tmp_path / "b" / "hogs" / "s01_box" / LIGHT_DIR / "light.safetensors").write_bytes(b"x")
    with pytest.raises(AssetError, match="light.safetensors does not match its sha256"):
        load_bundle(tmp_path / "b")
    assert load_bundle(bundle_dir).hogs[("s01", "box")].light is None
    shutil.copytree(bundle_dir, tmp_path / "c")
    shutil.copytree(run / LIGHT_DIR, tmp_path / "c" / "hogs" / "s01_box" / LIGHT_DIR)
    with pytest.raises(AssetError, match="light is not listed"):
        load_bundle(tmp_path / "c")
    # pre-1.0 (schema version 1) bundles are refused
    man = json.loads((bundle_dir / "manifest.json").read_text())
    shutil.rmtree(tmp_path / "c")
    shutil.copytree(bundle_dir, tmp_path / "c")
    (tmp_path / "c" / "manifest.json").write_text(json.dumps({**man, "schema_version": 1}))
    with pytest.raises(
        AssetError, match="(?s)invalid bundle.*unsupported schema_version 1; this reader supports 2; rebuild"
    ):
        load_bundle(tmp_path / "c")


def test_bundle_checks_its_checkpoints(bundle_dir, tiny_world, tmp_path):
    """SRM / ContactNet / pose banks are read as checkpoints when written and loaded; bank
    names are unique; a resolution-changing SRM fails at dataset construction."""
    run = bundle_dir / "hogs" / "s01_box"
    (tmp_path / "srm.bin").write_bytes(b"srm weights")
    (tmp_path / "notsrm").mkdir()
    for srm, match in (
        (tmp_path / "srm.bin", "must be a checkpoint folder"),
        (tmp_path / "notsrm", "manifest.json.*missing"),
        (tmp_path / "nope", "nope is missing"),
    ):
        with pytest.raises(AssetError, match=match):
            write_bundle(tmp_path / "b", tiny_world, [run], srm=srm)
    with pytest.raises(AssetError, match="ContactNet checkpoint.*manifest.json"):
        write_bundle(tmp_path / "b", tiny_world, [run], contactnet=tmp_path / "notsrm")
    (tmp_path / "s01" / "bank").mkdir(parents=True)
    (tmp_path / "s02" / "bank").mkdir(parents=True)
    with pytest.raises(AssetError, match="distinct folder names"):
        write_bundle(
            tmp_path / "b", tiny_world, [run], pose_banks=[tmp_path / "s01" / "bank", tmp_path / "s02" / "bank"]
        )
    assert not (tmp_path / "b").exists()  # nothing written
    # an SRM replaced inside a bundle (hashes updated) is still read as a checkpoint
    shutil.copytree(bundle_dir, tmp_path / "c")
    srm_dir = tmp_path / "c" / "srm" / "srm"
    (srm_dir / "manifest.json").write_text("{}")
    man = json.loads((tmp_path / "c" / "manifest.json").read_text())
    man["srm"]["files"] = {
        "manifest.json": hashlib.sha256(b"{}").hexdigest(),
        "srm.safetensors": man["srm"]["files"]["srm.safetensors"],
    }
    (tmp_path / "c" / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(AssetError, match="SRM checkpoint.*not an SRM checkpoint"):
        load_bundle(tmp_path / "c")
    # scale-2 SRM: refused when the dataset is made, naming its manifest
    b2 = write_bundle(tmp_path / "b2", tiny_world, [run], srm=tiny_srm(tmp_path / "srm2", scale=2))
    with pytest.raises(AssetError, match=r"srm2/manifest.json.*2x its input size"):
        _dataset(b2, tiny_world, srm=True)
    _dataset(bundle_dir, tiny_world, srm=True)  # scale 1: fine
    # test-time augmentation of the bundle's SRM
    from hogsa_loader.models.srm import load_srm

    with pytest.raises(ValueError, match="srm_tta must be one of"):
        _dataset(bundle_dir, tiny_world, srm=True, srm_tta=3)
    with pytest.raises(ValueError, match="srm_tta applies to the bundle's SRM"):
        _dataset(bundle_dir, tiny_world, srm_tta=4)
    refine = _dataset(bundle_dir, tiny_world, srm=True, srm_tta=8)._refiner(torch.device("cpu"))
    srm = load_srm(load_bundle(bundle_dir).srm.path)
    rgb, alpha = torch.rand(2, 24, 24, 3), torch.rand(2, 24, 24, 1)
    rgb = rgb * alpha
    torch.testing.assert_close(refine(rgb, alpha), srm.refine(rgb, alpha, tta=8), atol=1e-6, rtol=0)
    assert (refine(rgb, alpha) - srm.refine(rgb, alpha)).abs().max() > 1e-4  # (not the plain pass)


def test_dropped_samples_are_counted(bundle_dir, tiny_world):
    # cameras inside the scene: every sample is behind the camera, dropped before rendering
    ds = _dataset(
        bundle_dir, tiny_world, cameras=CameraConfig(distance_m=(0.001, 0.002), dataset_prob=0.0, target_jitter_m=0.0)
    )
    assert list(ds) == []
    assert ds.stats.dropped["behind_camera"] == 4 and ds.stats.kept == 0 and ds.stats.attempted == 4
    # an impossible alpha minimum: rendered, then dropped as empty
    ds = _dataset(bundle_dir, tiny_world, num_samples=2, batch_size=2, checks=SampleChecks(min_alpha_pixels=10**9))
    assert list(ds) == []
    assert ds.stats.dropped["empty_alpha"] == 2 and ds.stats.num_dropped == 2
    assert set(ds.stats.seconds) == {"pose", "pom", "render", "srm", "composite", "targets"}
    assert ds.stats.seconds["render"] > 0
    assert ds.total_stats().as_dict() == ds.stats.as_dict() and ds.worker_stats().attempted == 0
    # a NaN pose is dropped as "nan" (not as a pose behind the camera)
    inner = _dataset(bundle_dir, tiny_world)._pose_source

    class NaNPoses:
        keys = inner.keys

        def sample(self, key, rngs):
            batch = inner.sample(key, rngs)
            batch.poses["right_trans"][0] = float("nan")
            return batch

    ds = _dataset(bundle_dir, tiny_world, poses=NaNPoses())
    kept = list(ds)
    assert ds.stats.dropped["nan"] == 1 and ds.stats.dropped["behind_camera"] == 0 and len(kept) == ds.stats.kept == 3


def test_custom_pose_source_without_or_with_clashing_provenance(bundle_dir, tiny_world):
    """A pose source may give no provenance (PoseBatch's default); keys of its provenance
    never replace the sample's own identity (index, epoch, seed) in the frame's meta."""
    from hogsa_loader.sample.poses import PoseBatch

    inner = _dataset(bundle_dir, tiny_world)._pose_source
    ref = [f.meta for f in _dataset(bundle_dir, tiny_world, seed=5).frames(0) if f is not None]

    class Bare:
        keys = inner.keys

        def sample(self, key, rngs):
            return PoseBatch(inner.sample(key, rngs).poses)

    class Clashing(Bare):
        def sample(self, key, rngs):
            b = inner.sample(key, rngs)
            return PoseBatch(b.poses, [{**p, "index": 999, "seed": -1, "epoch": 7, "note": "x"} for p in b.provenance])

    bare = _dataset(bundle_dir, tiny_world, seed=5, poses=Bare())
    frames = bare.frames(0)
    assert bare.stats.attempted == 4 and bare.stats.kept + bare.stats.num_dropped == 4
    got = [f.meta for f in frames if f is not None]
    assert [m["index"] for m in got] == [m["index"] for m in ref] and all("pose_source" not in m for m in got)
    clash = [f.meta for f in _dataset(bundle_dir, tiny_world, seed=5, poses=Clashing()).frames(0) if f is not None]
    assert [(m["index"], m["seed"], m["epoch"]) for m in clash] == [(m["index"], 5, 0) for m in ref]
    assert all(m["note"] == "x" for m in clash)


def test_dropped_samples_are_counted_across_workers(bundle_dir, tiny_world):
    """Workers add their counters to the dataset's shared table; the main process sums them."""
    ds = _dataset(
        bundle_dir,
        tiny_world,
        num_samples=8,
        batch_size=2,
        cameras=CameraConfig(distance_m=(0.001, 0.002), dataset_prob=0.0, target_jitter_m=0.0),
    )
    for epoch in range(2):  # fresh workers each epoch: their counts add up
        ds.set_epoch(epoch)
        assert list(DataLoader(ds, batch_size=None, num_workers=2)) == []
    assert ds.stats.attempted == 0  # nothing rendered in this process
    w = ds.worker_stats()
    assert (
        w.attempted == 16 and w.dropped["behind_camera"] == 16 and w.kept == 0 and w.batches == ds.total_stats().batches
    )
    ok = _dataset(bundle_dir, tiny_world, num_samples=4, batch_size=2, seed=2)
    got = list(DataLoader(ok, batch_size=None, num_workers=2, persistent_workers=True))
    got += list(DataLoader(ok, batch_size=None, num_workers=1))
    t = ok.total_stats()
    assert t.kept == len(got) and t.attempted == 8 and t.kept + t.num_dropped == 8
    assert t.seconds["render"] > 0 and t.seconds["targets"] > 0


def test_wrap_train_loader_drop_in(bundle_dir, tiny_world):
    from hogsa_loader.integrations.arctic import wrap_train_loader

    real = DataLoader(ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0), batch_size=4)
    loader = wrap_train_loader(real, bundle_dir, ratio=0.25, batch_size=2, backgrounds=ProceduralBackgrounds())
    inputs, targets, meta = next(iter(loader))
    assert inputs["img"].shape == (4, 3, CFG.img_res, CFG.img_res)
    assert [is_synthetic(n) for n in meta["imgname"]] == [False, False, False, True]
    assert len(loader) == len(real.dataset) // 3
    # the real dataset's interaction-field setting carries over: both halves have its keys
    real = DataLoader(ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0, interfield=0.1), batch_size=4)
    loader = wrap_train_loader(real, bundle_dir, ratio=0.25, batch_size=2, backgrounds=ProceduralBackgrounds())
    _, targets, meta = next(iter(loader))
    assert "dist.ro" in targets and targets["dist.ro"].shape[0] == 4 and is_synthetic(meta["imgname"][3])
    assert float(targets["dist.ro"][3].max()) <= float(np.float32(0.1))  # the synthetic row is clamped as the real ones


def test_wrap_train_loader_reads_the_protocol(bundle_dir, tiny_world):
    """The synthetic half follows the real loader's protocol: ArcticDataset.setup, ARCTIC's
    own dataset (args.setup), through a Subset; p1a/p2a are p1/p2."""
    import types

    from torch.utils.data import Subset

    from hogsa_loader.integrations.arctic import wrap_train_loader

    real = ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0)
    kw = dict(ratio=0.5, batch_size=2, backgrounds=ProceduralBackgrounds(), data_root=tiny_world)
    arctic_own = types.SimpleNamespace(args=types.SimpleNamespace(setup="p2a"), __len__=lambda: 4)
    cases = (
        (real, "p1"),
        (Subset(real, [0, 1, 2, 3]), "p1"),
        (types.SimpleNamespace(setup="p1a"), "p1"),
        (arctic_own, "p2"),
        (types.SimpleNamespace(setup="p2"), "p2"),
    )
    for ds, want in cases:
        loader = wrap_train_loader(types.SimpleNamespace(dataset=ds, batch_size=2), bundle_dir, **kw)
        assert loader.synthetic.protocol == want, (ds, want)
    # an unknown setup is left to the caller
    odd = types.SimpleNamespace(dataset=types.SimpleNamespace(setup="p9"), batch_size=2)
    assert wrap_train_loader(odd, bundle_dir, protocol="p2", **kw).synthetic.protocol == "p2"
    assert wrap_train_loader(odd, bundle_dir, **kw).synthetic.protocol == "p1"
    assert wrap_train_loader(odd, bundle_dir, **kw).mode == "replace"
    assert wrap_train_loader(odd, bundle_dir, mode="add", **kw).mode == "add"


def test_pose_bank_source(bundle_dir, tiny_world, tmp_path):
    """poses="bank" serves accepted POM-bank rows of the right (subject, object), unchanged."""
    from hogsa_loader.models.bundle import load_bundle
    from hogsa_loader.models.pom.bank import save_pose_bank
    from hogsa_loader.models.pom.state import load_frames
    from hogsa_loader.sample.bank_poses import BankPoses
    from hogsa_loader.sample.poses import PoseContext

    root = ArcticRoot(tiny_world)
    seq = [s for s in root.sequences("s01") if s.split("/")[1].startswith("box")][0]
    state, src = load_frames(root, [seq], stride=16)
    n = state.batch
    assert n >= 2
    accept = np.zeros(n, np.float32)
    accept[1] = 1.0  # only row 1 passed acceptance
    zeros = np.zeros(n, np.float32)
    metrics = {"penetration_depth": zeros, "intersection": zeros, "contact_ratio": zeros, "accept": accept}
    save_pose_bank(tmp_path / "bank", state, src, metrics)
    ctx = PoseContext(root=root, keys=[("s01", "box")], bundle=load_bundle(bundle_dir))
    with pytest.raises(AssetError, match="needs a pose bank"):
        BankPoses(ctx)
    src_bank = BankPoses(ctx, banks=[tmp_path / "bank"])
    assert len(src_bank) == 1 and src_bank.keys == [("s01", "box")]
    batch = src_bank.sample(("s01", "box"), [np.random.default_rng(i) for i in range(3)])
    assert len(batch) == 3 and all(p["row"] == 1 and p["pose_source"] == "bank" for p in batch.provenance)
    torch.testing.assert_close(batch.poses["right_pose"][0], state.hands["right"].pose[1].double())
    torch.testing.assert_close(batch.poses["obj_trans"][2], state.obj_trans[1].double())
    assert batch.poses["obj_arti"].shape == (3, 1)
    with pytest.raises(AssetError, match="no accepted grasp"):
        BankPoses(PoseContext(root=root, keys=[("s05", "box")]), banks=[tmp_path / "bank"])
    # end to end: the dataset renders bank poses
    ds = _dataset(bundle_dir, tiny_world, poses="bank", pose_options={"banks": [tmp_path / "bank"]})
    fr = [f for f in ds.frames(0) if f is not None]
    assert fr and all(f.meta["pose_source"] == "bank" and f.meta["row"] == 1 for f in fr)


def test_online_pose_source(bundle_dir, tiny_world, tmp_path):
    """poses="online": seeded perturbation + batched POM per render batch, reproducible,
    POM-dropped samples counted, and the optimisation moves the hands off the source frame."""
    from hogsa_loader.models.bundle import load_bundle
    from hogsa_loader.models.pom.contactnet import ContactNet, ContactNetConfig, save_contactnet
    from hogsa_loader.sample.online_poses import OnlinePoses
    from hogsa_loader.sample.poses import PoseContext

    root = ArcticRoot(tiny_world)
    ctx = PoseContext(root=root, keys=[("s01", "box")], bundle=load_bundle(bundle_dir))
    with pytest.raises(AssetError, match="needs a ContactNet"):
        OnlinePoses(ctx)
    torch.manual_seed(0)
    save_contactnet(ContactNet(ContactNetConfig()), tmp_path / "cn", {})
    src = OnlinePoses(ctx, contactnet=tmp_path / "cn", iters=5)
    rngs = lambda: [np.random.default_rng([9, i]) for i in range(3)]  # noqa: E731
    raw = src.sample(("s01", "box"), rngs())
    assert all(p["pose_source"] == "online" and "pom_seed" in p for p in raw.provenance)
    fr = src.frames[("s01", "box")]
    r0 = raw.provenance[0]["row"]
    torch.testing.assert_close(raw.poses["right_trans"][0], fr.state.hands["right"].trans[r0].double())
    a = src.optimize(("s01", "box"), raw)
    b = src.optimize(("s01", "box"), src.sample(("s01", "box"), rngs()))
    for k in a.poses:
        torch.testing.assert_close(a.poses[k], b.poses[k])  # same seeds -> same grasps
    moved = (a.poses["right_trans"] - raw.poses["right_trans"]).norm(dim=1)
    assert (moved > 1e-4).all()  # perturbed + optimised, not the source frame
    # the object stays where the (seeded) perturbation put it: POM optimises the hands only
    from hogsa_loader.models.pom.perturb import perturb

    start = perturb(
        fr.state.select([r0]),
        src.infos,
        src.objects,
        torch.Generator().manual_seed(raw.provenance[0]["pom_seed"]),
        src.perturb_config,
    )[0]
    torch.testing.assert_close(a.poses["obj_trans"][:1], start.obj_trans.double())
    torch.testing.assert_close(a.poses["obj_rot"][:1], start.obj_rot.double())
    # end to end through the dataset: the POM stage is timed, every attempt kept or counted
    ds = _dataset(bundle_dir, tiny_world, poses="online", pose_options={"contactnet": tmp_path / "cn", "iters": 3})
    frames = ds.frames(0)
    st = ds.stats
    assert st.seconds.get("pom", 0.0) > 0
    assert sum(f is not None for f in frames) + sum(st.dropped.values()) == st.attempted == 4
    assert all(f.meta["pose_source"] == "online" for f in frames if f is not None)


def test_interfield_targets_on_synthetic_and_real_samples_match(bundle_dir, tiny_world):
    """interfield=True adds the same keys, shapes and dtypes to synthetic and real samples,
    and the synthetic field is that of the rendered (posed) meshes."""
    from hogsa_loader.sample.interfield import INTERFIELD_KEYS

    ds = _dataset(bundle_dir, tiny_world, interfield=True, seed=5)
    fr = [f for f in ds.frames(0) if f is not None]
    assert fr
    syn = ds.to_sample(fr[0])
    real = ArcticDataset(tiny_world, split="p1_train", config=CFG, interfield=True)[0]
    for s, r in zip(syn, real):
        assert list(s) == list(r)  # same keys, same order
        for k in r:
            assert _describe(s[k]) == _describe(r[k]), k
    assert set(INTERFIELD_KEYS) <= set(syn[1])
    # the grasp source frames touch the object: some hand vertex within a centimetre
    assert min(float(syn[1]["dist.ro"].min()), float(syn[1]["dist.lo"].min())) < 0.01


def test_egocentric_protocol_p2(bundle_dir, tiny_world):
    """protocol="p2": the subject's head camera, the whole frame; samples match real p2
    samples key for key (egocentric patch K, dist kept), pinhole labels lie on the alpha,
    and the lens distortion moves pixels but never labels (ARCTIC's view-0 convention)."""
    kw = dict(protocol="p2", seed=2, num_samples=8)
    pin = _dataset(bundle_dir, tiny_world, ego_distortion=False, **kw)
    dis = _dataset(bundle_dir, tiny_world, ego_distortion=True, **kw)
    fp = [f for f in pin.frames(0) if f is not None]
    fd = [f for f in dis.frames(0) if f is not None]
    assert len(fp) >= 3 and [f.imgname for f in fp] == [f.imgname for f in fd]
    real = ArcticDataset(tiny_world, split="p2_train", config=CFG, seed=0)[0]
    syn = pin.to_sample(fp[0])
    for s, r in zip(syn, real):
        assert list(s) == list(r)
        for k in r:
            assert _describe(s[k]) == _describe(r[k]), k
    torch.testing.assert_close(syn[2]["intrinsics"], real[2]["intrinsics"])  # same ego camera, same patch K
    assert np.isfinite(np.asarray(syn[2]["dist"])).all()
    # the box centre is the frame centre, in pixels of each one's image (sizes differ)
    W = fp[0].image.shape[1]
    cs, cr = np.asarray(syn[2]["center"], np.float64), np.asarray(real[2]["center"], np.float64)
    assert cs[0] == pytest.approx(W / 2) and cs[1] / cs[0] == pytest.approx(cr[1] / cr[0], rel=1e-3)
    hits = []
    for a, b in zip(fp, fd):
        assert a.egocentric and a.meta["camera"] == "egocentric" and a.meta["view"] == 0
        W = a.image.shape[1]
        assert W == pin.render_size and a.bbox[2] * 200 == pytest.approx(W)  # whole frame, side = width
        np.testing.assert_array_equal(a.right.j2d, b.right.j2d)  # labels: undistorted either way
        assert np.abs(a.alpha - b.alpha).max() > 0.1  # pixels: distorted in one of them
        for h in (a.right, a.left):
            ok = (h.j2d >= 0).all(1) & (h.j2d[:, 0] <= W - 1) & (h.j2d[:, 1] <= a.image.shape[0] - 1)
            hits.extend(joints_on_alpha(h.j2d[ok], a.alpha, radius=0))
    assert len(hits) >= 60 and float(np.mean(hits)) >= 0.99
    assert pin.aug_params(3).sc == 1.0  # ARCTIC forces sc = 1 for egocentric samples


def test_explicit_objects_refuse_settings_of_their_config_group(bundle_dir, tiny_world):
    """An explicit backgrounds / poses / refiner object replaces its config group; non-default
    settings of that group beside it are refused, not silently ignored."""
    procedural = ProceduralBackgrounds()
    with pytest.raises(ValueError, match="backgrounds= is given together with non-default config.backgrounds"):
        HOGSADataset(bundle_dir, tiny_world, _config(background_folder="x"), backgrounds=procedural)
    with pytest.raises(ValueError, match="refiner= is given together with non-default config.refinement"):
        HOGSADataset(bundle_dir, tiny_world, _config(srm=True), backgrounds=procedural, refiner=lambda rgb, a: rgb)
    inner = _dataset(bundle_dir, tiny_world)._pose_source
    with pytest.raises(ValueError, match="poses= is given together with non-default config.poses"):
        HOGSADataset(bundle_dir, tiny_world, _config(poses="bank"), backgrounds=procedural, poses=inner)
    with pytest.raises(TypeError, match="unknown loader option"):
        with_options(sed=1)
    ds = _dataset(bundle_dir, tiny_world, seed=9, batch_size=3, num_samples=8)
    plan = ds.plan(2, epoch=4)
    assert (plan.seed, plan.epoch, plan.key, plan.indices) == (9, 4, ds.batch_key(2, 4), (6, 7))


def test_export_info_records_every_setting_that_changes_the_frames():
    """The recorded settings are every loader option, default or not, except the device and the
    sample count (which do not change the frames); an option set elsewhere is recorded as set."""
    import dataclasses

    from hogsa_loader.sample.config import export_info

    def leaves(cfg) -> set[str]:
        out = set()
        for f in dataclasses.fields(cfg):
            value = getattr(cfg, f.name)
            if f.metadata.get("flat"):
                out |= leaves(value)
            else:
                out.add(f.metadata.get("name", f.name))
        return out

    recorded = set(export_info(LoaderConfig()))
    assert recorded == leaves(LoaderConfig()) - {"device", "num_samples"}
    assert {"seed", "poses", "srm", "cameras", "checks", "exclude_person", "subjects", "other_hands"} <= recorded
    info = export_info(
        with_options(
            exclude_person=True, srm=True, srm_tta=8, cameras=CameraConfig(roll_deg=0.0), device="cuda", num_samples=5
        )
    )
    assert info["exclude_person"] is True and info["srm_tta"] == 8 and info["cameras"]["roll_deg"] == 0.0
    assert "device" not in info and "num_samples" not in info
    assert export_info(LoaderConfig())["exclude_person"] is False


def test_dataset_camera_samples_sit_on_their_own_plate(bundle_dir, tiny_world, tmp_path):
    """With camera plates, a sample rendered through a dataset camera is composited on that
    camera's plate cut by the sample's own crop box (its labels' box), pixel for pixel."""
    from hogsa_loader.assets.conventions import full_to_cropped
    from hogsa_loader.compose import PlateBackgrounds
    from hogsa_loader.compose.plates import PlateConfig, build_plates

    build_plates(PlateConfig(data=str(tiny_world), out=str(tmp_path), width=240, frames_per_sequence=2, quiet=True))
    src = PlateBackgrounds(tmp_path)
    calls = []
    plate_of = src.camera_plate

    def recorded(subject, view, box, size):
        out = plate_of(subject, view, box, size)
        calls.append((subject, view, np.array(box), out))
        return out

    src.camera_plate = recorded
    ds = _dataset(bundle_dir, tiny_world, backgrounds=src, cameras=CameraConfig(dataset_prob=1.0), num_samples=4)
    frames = [f for f in ds.frames(0) if f is not None]
    assert frames and calls
    for f in frames:
        assert f.meta["view"] != NOVEL_VIEW
        bg = f.alpha == 0
        assert bg.mean() > 0.2
        match = [c for c in calls if c[3] is not None and np.array_equal(f.image[bg], c[3][bg])]
        assert len(match) >= 1 and match[0][:2] == (f.meta["subject"], f.meta["view"])
        # the plate was cut by this sample's crop box: its labels are the full-image joints cropped by it
        full2d = f.right.j3d_full @ f.K_full.T
        full2d = full2d[:, :2] / full2d[:, 2:]
        np.testing.assert_allclose(full_to_cropped(full2d, match[0][2], f.image.shape[0]), f.right.j2d, atol=1e-3)


def test_an_annotated_pose_through_its_own_camera_carries_the_real_frames_labels(bundle_dir, tiny_world):
    """A synthetic sample of an annotated training pose seen through that frame's own capture
    camera carries exactly the targets of the real frame of the same (sequence, frame, view):
    3D joints and object keypoints in the camera frame, MANO parameters, articulation, and the
    2D joints and keypoints in the crop (the dataset's crop box)."""
    ds = _dataset(
        bundle_dir,
        tiny_world,
        poses="perturb",
        pose_options={"finger_std": 0.0},
        cameras=CameraConfig(dataset_prob=1.0),
        augment=False,
        num_samples=8,
        batch_size=8,
    )
    real = ArcticDataset(tiny_world, split="p1_train", augment=False, seed=0, config=CFG)
    misc = ArcticRoot(tiny_world).misc()
    by_name = {}
    for i, name in enumerate(real.imgnames):
        sid, seq, view, stem = name.split("/")[-4:]
        by_name[(sid, seq, int(view), int(stem.split(".")[0]))] = i
    keys = [
        "mano.j3d.full.r",
        "mano.j3d.full.l",
        "object.kp3d.full.b",
        "object.bbox3d.full.t",
        "mano.pose.r",
        "mano.pose.l",
        "mano.beta.r",
        "object.radian",
        "object.rot",
        "mano.j2d.norm.r",
        "mano.j2d.norm.l",
        "object.kp2d.norm.b",
    ]
    compared = 0
    for frame in ds.frames(0):
        if frame is None:
            continue
        sid, seq = frame.meta["sequence"].split("/")
        key = (sid, seq, int(frame.meta["view"]), int(frame.meta["frame"]) + misc[sid].ioi_offset)
        if key not in by_name:  # a frame outside the split's range
            continue
        _, syn, _ = ds.sample(int(frame.meta["index"]))
        _, ref, _ = real[by_name[key]]
        for k in keys:
            np.testing.assert_allclose(np.asarray(syn[k]), np.asarray(ref[k]), atol=1e-5, err_msg=f"{k} of {key}")
        compared += 1
    assert compared >= 4


@pytest.fixture(scope="module")
def two_subject_dir(tiny_world, tmp_path_factory) -> Path:
    """Untrained runs of s01/box and s05/box whose hands differ only in colour (s05's red)."""
    from hogsa_world.untrained import write_untrained_run

    out = tmp_path_factory.mktemp("two_subjects")
    runs = [
        write_untrained_run(tiny_world, out / "runs" / f"{sid}_box", sid, "box", hand_rgb=rgb)
        for sid, rgb in (("s01", None), ("s05", (0.9, 0.1, 0.1)))
    ]
    return write_bundle(out / "bundle", tiny_world, runs)


def test_held_out_subjects_models_stream_only_when_named(bundle_dir, two_subject_dir, tiny_world):
    """The tiny world holds s05 out (p1 val): its model in a bundle is left out of the stream
    with a warning, refused when asked for by ``subjects`` alone, and streamed (with a
    ``HeldOutWarning``) only when named in ``allow_held_out``."""
    with pytest.warns(UserWarning, match=r"models of \['s05'\], held out"):
        default = _dataset(two_subject_dir, tiny_world)
    assert default.keys == [("s01", "box")]
    assert {default.batch_key(g, 0) for g in range(8)} == {("s01", "box")}
    with pytest.raises(UsageError, match=r"s05 \(val\) held out"):
        _dataset(two_subject_dir, tiny_world, subjects=("s05",))
    with pytest.raises(UsageError, match="does not hold out"):
        _dataset(two_subject_dir, tiny_world, allow_held_out=("s01",))
    with pytest.warns(HeldOutWarning, match="s05"):
        named = _dataset(
            two_subject_dir,
            tiny_world,
            poses=_S01Poses(_dataset(bundle_dir, tiny_world)._pose_source),
            allow_held_out=("s05",),
        )
    assert named.keys == [("s01", "box"), ("s05", "box")]
    s05_only = write_bundle(
        two_subject_dir.parent / "s05_only", tiny_world, [two_subject_dir.parent / "runs" / "s05_box"]
    )
    with pytest.warns(UserWarning), pytest.raises(ValueError, match=r"no HOGS model left .*held out: \['s05'\]"):
        _dataset(s05_only, tiny_world)


class _S01Poses:
    """s01's annotated poses for both models (the cameras stay each subject's own)."""

    keys = [("s01", "box"), ("s05", "box")]

    def __init__(self, inner):
        self.inner = inner

    def sample(self, key, rngs):
        return self.inner.sample(("s01", "box"), rngs)


def test_other_hands_change_the_hands_pixels_and_nothing_else(bundle_dir, two_subject_dir, tiny_world):
    """With ``other_hands=1`` every render batch shows the other subject's hand Gaussians:
    the labels, the alpha and every pixel away from the hands stay those of the model's own
    hands, the hands take the other run's colour, and the frame records whose hands it shows."""
    inner = _dataset(bundle_dir, tiny_world)._pose_source
    kw = dict(poses=_S01Poses(inner), num_samples=8, batch_size=4, seed=5, allow_held_out=("s05",))
    own = _dataset(two_subject_dir, tiny_world, **kw)
    other = _dataset(two_subject_dir, tiny_world, other_hands=1.0, **kw)
    compared = {"s01": 0, "s05": 0}
    for g in range(2):
        p0, p1 = own.plan(g), other.plan(g)
        assert p0.key == p1.key and p0.hands is None
        assert p1.hands == ("s05" if p1.key[0] == "s01" else "s01", "box")
        for f0, f1 in zip(own.render(p0), other.render(p1)):
            if f0 is None or f1 is None:
                continue
            assert f1.meta["hands_from"] == "/".join(p1.hands) and "hands_from" not in f0.meta
            for side in ("right", "left"):
                np.testing.assert_array_equal(getattr(f1, side).j2d, getattr(f0, side).j2d)
            np.testing.assert_allclose(f1.alpha, f0.alpha, atol=1e-6)
            np.testing.assert_allclose(f1.part_alpha, f0.part_alpha, atol=1e-6)
            hand = f0.part_alpha[..., :2].sum(-1)
            away = hand < 1e-4
            diff = np.abs(f1.image.astype(int) - f0.image.astype(int))
            assert diff[away].max() <= 1  # background and object: the same pixels
            on = hand > 0.9
            assert on.sum() > 20
            red = [f.image[on].astype(float) @ np.array([1.0, -0.5, -0.5]) for f in (f0, f1)]
            if p1.key[0] == "s01":  # s05's red hands on s01's model
                assert red[1].mean() > red[0].mean() + 40
            else:
                assert red[1].mean() < red[0].mean() - 40
            compared[p1.key[0]] += 1
    assert min(compared.values()) > 0
    half = _dataset(two_subject_dir, tiny_world, other_hands=0.5, **{**kw, "num_samples": None})
    plans = [half.plan(g) for g in range(16)]
    swapped = next(p for p in plans if p.hands is not None)
    mixed = [swapped, next(p for p in plans if p.hands is None and p.key == swapped.key)]
    for plan in mixed:  # one pipeline, both kinds of batch of one model: each renders as its kind's dataset does
        twin = own if plan.hands is None else other
        for f, g in zip(half.render(plan), twin.render(plan)):
            assert (f is None) == (g is None)
            if f is not None:
                np.testing.assert_array_equal(f.image, g.image)
    index = other.batch_indices(1)[0]
    again = other.sample(index)
    streamed = next(s for s in other.samples(1) if s[2]["imgname"] == again[2]["imgname"])
    torch.testing.assert_close(again[0]["img"], streamed[0]["img"])  # one sample alone: the same hands


def test_other_hands_share_is_drawn_per_batch_and_needs_two_subjects(bundle_dir, two_subject_dir, tiny_world):
    inner = _dataset(bundle_dir, tiny_world)._pose_source
    kw = dict(poses=_S01Poses(inner), num_samples=8, batch_size=4, allow_held_out=("s05",))
    half = _dataset(two_subject_dir, tiny_world, other_hands=0.5, seed=5, **kw)
    hands = [half.batch_hands(g, 0) for g in range(400)]
    swapped = [h is not None for h in hands]
    assert 0.4 < np.mean(swapped) < 0.6
    for g, h in enumerate(hands):
        assert h is None or h[0] != half.batch_key(g, 0)[0]
    again = _dataset(two_subject_dir, tiny_world, other_hands=0.5, seed=5, **kw)
    assert [again.batch_hands(g, 0) for g in range(400)] == hands  # a function of (seed, epoch, batch)
    assert [half.batch_hands(g, 1) for g in range(400)] != hands
    seed6 = _dataset(two_subject_dir, tiny_world, other_hands=0.5, seed=6, **kw)
    assert [seed6.batch_hands(g, 0) for g in range(400)] != hands
    with pytest.raises(ValueError, match="one subject"):
        _dataset(bundle_dir, tiny_world, other_hands=0.5)
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        _config(other_hands=1.5)
    assert (
        export_info(_config())["other_hands"] == 0.0 and export_info(_config(other_hands=0.25))["other_hands"] == 0.25
    )


def test_hands_run_prefers_the_same_object_then_the_subjects_first_run():
    from hogsa_loader.models.gaussians.recombine import hands_run

    keys = [("s02", "notebook"), ("s01", "laptop"), ("s02", "box"), ("s01", "box")]
    assert hands_run(keys, "s02", "box") == ("s02", "box")
    assert hands_run(keys, "s02", "laptop") == ("s02", "box")  # no laptop run: its first in sorted order
    assert hands_run(keys, "s03", "box") is None


def test_a_stream_that_keeps_nothing_stops_with_the_reasons(bundle_dir, tiny_world):
    """An endless stream whose every sample is dropped (here: no sample can show 10⁹ alpha
    pixels) raises after ``max_consecutive_drops`` drops in a row instead of rendering forever."""
    from hogsa_loader.sample.config import SampleChecks
    from hogsa_loader.sample.dataset import DroppedSamplesError

    checks = SampleChecks(min_alpha_pixels=10**9, max_consecutive_drops=6)
    ds = _dataset(bundle_dir, tiny_world, num_samples=None, batch_size=4, checks=checks)
    with pytest.raises(DroppedSamplesError, match=r"6 synthetic samples in a row were dropped .*empty_alpha 8"):
        next(iter(ds))
    assert ds.stats.attempted == 8 and ds.stats.kept == 0


def test_drop_guard_counts_drops_in_a_row_and_warns_once_on_a_high_share():
    from hogsa_loader.sample.config import SampleChecks
    from hogsa_loader.sample.dataset import DropGuard, DroppedSamplesError
    from hogsa_loader.sample.synth import SynthStats

    stats = SynthStats()
    stats.dropped["empty_alpha"] = 5  # counted before the stream started (a worker's copy of its parent's counts)
    guard = DropGuard(SampleChecks(max_consecutive_drops=3, warn_drop_share=0.5), stats)
    stats.dropped["out_of_crop"] = 3  # counted by this stream
    kept = object()
    with pytest.warns(UserWarning, match="dropped") as caught:
        for _ in range(200):  # two drops, then a kept sample: never three in a row
            guard.update([None, None, kept])
    assert len([w for w in caught if "synthetic samples were dropped" in str(w.message)]) == 1
    assert guard.seen == 600 and guard.dropped == 400 and guard.warned  # warned once (share 2/3 > 0.5)
    with pytest.raises(DroppedSamplesError, match=r"3 synthetic samples in a row .*by reason: out_of_crop 3\)") as info:
        guard.update([None, None, None])
    assert "empty_alpha" not in str(info.value)
    with pytest.raises(ValueError, match="max_consecutive_drops"):
        SampleChecks(max_consecutive_drops=0)
    with pytest.warns(UserWarning, match="400 of 600 synthetic samples were dropped"):
        DropGuard(SampleChecks(max_consecutive_drops=3), stats).update([None, None, kept] * 200)


class _Epochs(torch.utils.data.Dataset):
    """Items ``epoch * 100 + i``: what ``set_epoch`` reached shows in every sample."""

    def __init__(self, n: int) -> None:
        self.n, self.epoch = n, 0

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        return {"x": torch.tensor(self.epoch * 100 + i)}

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch


class _Stream:
    """Endless synthetic samples ``-(epoch * 100 + k) - 1`` from the start of the set epoch."""

    def __init__(self) -> None:
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self):
        return ({"x": torch.tensor(-(self.epoch * 100 + k) - 1)} for k in itertools.count())


def test_mixed_loader_set_epoch_reaches_the_sampler_the_dataset_and_the_stream():
    from torch.utils.data import DistributedSampler

    ds = _Epochs(8)
    sampler = DistributedSampler(ds, num_replicas=2, rank=1, shuffle=True, seed=0)
    mixed = MixedLoader(DataLoader(ds, batch_size=2, sampler=sampler), _Stream(), ratio=0.5)
    first = [b["x"].tolist() for b in mixed]
    mixed.set_epoch(3)
    again = [b["x"].tolist() for b in mixed]
    assert sampler.epoch == 3 and ds.epoch == 3 and mixed.synthetic.epoch == 3
    order = list(sampler)  # the shuffled order of epoch 3, rank 1's share
    assert [b[0] for b in again] == [300 + i for i in order]  # real half: epoch 3's order, epoch 3's draws
    assert [b[1] for b in again] == [-301 - k for k in range(4)]  # synthetic half: epoch 3, from its start
    assert [b[1] for b in first] == [-1 - k for k in range(4)]
    sampler.set_epoch(0)
    assert [b[0] for b in first] == list(sampler)


@pytest.mark.cuda
def test_mixed_batches_are_pinned_when_the_real_loader_pins():
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    real = DataLoader(_Epochs(4), batch_size=2, pin_memory=True)
    batch = next(iter(MixedLoader(real, _Stream(), ratio=0.5)))
    assert batch["x"].is_pinned()


def test_wrap_train_loader_takes_the_papers_method_where_the_bundle_has_it(bundle_dir, tiny_world):
    """By default the paper's method as far as the bundle holds it (its SRM; bank poses only with
    a pose bank); the named presets ask for their parts and refuse a bundle without them."""
    import dataclasses

    from hogsa_loader.integrations.arctic import method_options, wrap_train_loader

    real = DataLoader(ArcticDataset(tiny_world, split="p1_train", config=CFG, seed=0), batch_size=4)
    kw = dict(ratio=0.5, batch_size=2, backgrounds=ProceduralBackgrounds())
    b = load_bundle(bundle_dir)
    assert b.srm is not None and not b.pose_banks  # the test bundle: an SRM, no pose bank
    syn = wrap_train_loader(real, bundle_dir, **kw).synthetic
    assert (syn.config.poses.kind, syn.config.refinement.srm) == ("perturb", True)
    syn = wrap_train_loader(real, bundle_dir, method="no_pom", **kw).synthetic
    assert (syn.config.poses.kind, syn.config.refinement.srm) == ("perturb", True)
    assert wrap_train_loader(real, bundle_dir, srm=False, **kw).synthetic.config.refinement.srm is False
    with pytest.raises(ValueError, match="needs a pose bank"):
        wrap_train_loader(real, bundle_dir, method="hogsa", **kw)
    with pytest.raises(ValueError, match="conflicting options"):
        wrap_train_loader(real, bundle_dir, method="no_pom", srm=False, **kw)
    with_bank = dataclasses.replace(b, pose_banks={"pose_bank": object()})
    assert method_options("hogsa", with_bank) == {"poses": "bank", "srm": True}
    assert method_options("no_srm", with_bank) == {"poses": "bank", "srm": False}
    with pytest.raises(ValueError, match="needs an SRM"):
        method_options("no_pom", dataclasses.replace(b, srm=None))
    still = method_options("views_only", b)
    assert still["poses"] == "perturb" and still["srm"] is True
    assert set(still["pose_options"].values()) == {0.0}
    syn = wrap_train_loader(real, bundle_dir, method="views_only", **kw).synthetic
    assert syn.config.poses.options == still["pose_options"]
    batch = syn._pose_source.sample(("s01", "box"), [np.random.default_rng(i) for i in range(3)])
    for i, prov in enumerate(batch.provenance):  # each grasp is an annotated frame's, exactly
        sid, seq = prov["sequence"].split("/")
        hand = ArcticRoot(tiny_world).sequence(sid, seq).right
        assert np.array_equal(batch.poses["right_pose"][i], hand.pose[prov["frame"]])
    assert len(next(iter(wrap_train_loader(real, bundle_dir, method="views_only", **kw)))[2]["imgname"]) == 4
    with pytest.raises(ValueError, match="one of"):
        method_options("novel", b)
