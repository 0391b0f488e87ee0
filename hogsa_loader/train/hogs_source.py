"""Where a HOGS run's images, hands and object come from: an ARCTIC(-format) or an H2O root.

:func:`open_hogs_source` gives one :class:`HogsSource` for both datasets (its docstring
compares them), so the trainer and ``experiments/render_quality.py`` build the same split
and the same models; :func:`load_run_data` reopens a run's dataset from its ``config.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Optional

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import ALLO_VIEWS
from hogsa_loader.assets.h2o import H2ORoot
from hogsa_loader.assets.h2o_meshes import h2o_class_name, h2o_mesh_provenance, load_h2o_object
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.template import ObjectTemplate
from hogsa_loader.assets.roots import DATASETS
from hogsa_loader.errors import PathLike
from hogsa_loader.train.hogs_data import FrameSelection, HogsData, load_hogs_data
from hogsa_loader.train.hogs_data_h2o import H2O_EVAL_VIEWS, H2O_VIEWS, load_h2o_hogs_data

__all__ = ["DATASETS", "HogsSource", "open_hogs_source", "mano_layers_from_dir", "load_run_data"]


@dataclass
class HogsSource:
    """One opened dataset root with the models a run needs.

    Attributes:
        dataset: ``"arctic"`` or ``"h2o"``.
        root: :class:`~hogsa_loader.assets.arctic.ArcticRoot` or
            :class:`~hogsa_loader.assets.h2o.H2ORoot`.
        mano_layers: ``{"right", "left"}`` MANO layers (``flat_hand_mean=False``).
        object_templates: ``{name: ObjectTemplate}`` (ARCTIC: every template of the root;
            H2O: the requested object), what :meth:`HogsModel.from_run` takes.
        object_provenance: where the trained object's mesh came from (run manifests).
        views, eval_views: default camera views and held-out views.
    """

    dataset: str
    root: Any
    mano_layers: dict
    object_templates: Mapping[str, ObjectTemplate]
    object_provenance: dict[str, str] = field(default_factory=dict)
    views: tuple[int, ...] = ALLO_VIEWS
    eval_views: tuple[int, ...] = (8,)

    def load(
        self,
        subject: str,
        object_name: str,
        selection: Optional[FrameSelection] = None,
        *,
        masks: str = "auto",
        window: str = "crop",
    ) -> HogsData:
        """The training / held-out split.

        Args:
            selection: frames, views and resolution (unset or empty views / eval_views: the
                dataset's defaults).
            masks: ``"auto"``, ``"files"`` or ``"render"`` (H2O: never files).
            window: ``"crop"`` or ``"fg"`` (ARCTIC only, see :func:`~hogsa_loader.train.hogs_data.load_hogs_data`).
        """
        sel = selection or FrameSelection()
        sel = replace(sel, views=tuple(sel.views or self.views), eval_views=tuple(sel.eval_views or self.eval_views))
        if self.dataset == "arctic":
            return load_hogs_data(self.root, subject, object_name, sel, masks=masks, window=window)
        if window != "crop":
            raise ValueError(f"window={window!r} is implemented for ARCTIC only (H2O trains on whole crops)")
        if masks == "files":
            raise ValueError("H2O ships no masks: use masks='render' (or 'auto')")
        if object_name not in self.object_templates:
            raise ValueError(f"object {object_name!r} was not opened (have {sorted(self.object_templates)})")
        return load_h2o_hogs_data(
            self.root,
            subject,
            object_name,
            mano_layers=self.mano_layers,
            template=self.object_templates[object_name],
            selection=sel,
        )


def mano_layers_from_dir(mano_dir: PathLike) -> dict:
    """``{"right", "left"}`` MANOLayers (``flat_hand_mean=False``) of ``MANO_RIGHT/LEFT`` in a folder."""
    return {side: MANOLayer(load_mano(mano_dir, side=side), flat_hand_mean=False).eval() for side in ("right", "left")}


def open_hogs_source(
    dataset: str,
    data: PathLike,
    object_name: str,
    *,
    mano_dir: Optional[PathLike] = None,
    object_mesh_dir: Optional[PathLike] = None,
) -> HogsSource:
    """Open a dataset root for a run on ``object_name``.

    The two datasets:

    =============  ==========================================  ================================
                   ``arctic``                                  ``h2o``
    =============  ==========================================  ================================
    data           ARCTIC ``./data`` (or the generated world)  H2O root (``subjectN/...``)
    MANO           ``body_models/mano`` of the root            ``mano_dir`` (required)
    object         ``meta/object_vtemplates/<object>``         ``object_mesh_dir`` (required),
                                                               :mod:`~hogsa_loader.assets.h2o_meshes`
    views          allocentric 1–8, held out: 8                static cameras 0–3, held out: 3
    masks          ``masks/`` files, else rendered              always rendered
    =============  ==========================================  ================================

    MANO layers are built with ``flat_hand_mean=False`` for both (the
    :class:`~hogsa_loader.assets.types.HandTrack` convention; H2O's flat-mean labels are
    converted by :class:`~hogsa_loader.assets.h2o.H2ORoot`).

    Raises:
        ValueError: unknown dataset, an H2O option given for ARCTIC, a missing H2O option,
            or an unknown H2O object.
        AssetError: unreadable roots, models or meshes (names the file).
    """
    if dataset not in DATASETS:
        raise ValueError(f"dataset must be one of {DATASETS}, got {dataset!r}")
    if dataset == "arctic":
        if mano_dir is not None or object_mesh_dir is not None:
            raise ValueError(
                "--mano-dir / --object-mesh-dir are H2O options; an ARCTIC root has "
                "body_models/mano and meta/object_vtemplates"
            )
        root = ArcticRoot(data)
        templates = root.object_templates()
        prov = {"template": str(root.meta_dir / "object_vtemplates" / object_name)} if object_name in templates else {}
        return HogsSource("arctic", root, root.mano_layers(), templates, prov)
    missing = [opt for opt, val in (("--mano-dir", mano_dir), ("--object-mesh-dir", object_mesh_dir)) if val is None]
    if missing:
        raise ValueError(f"dataset 'h2o' needs {' and '.join(missing)} (H2O ships no MANO models or object meshes)")
    assert mano_dir is not None and object_mesh_dir is not None
    if h2o_class_name(object_name) != object_name:
        raise ValueError(f"name the H2O object by its class name {h2o_class_name(object_name)!r}, not {object_name!r}")
    root = H2ORoot(data)
    template = load_h2o_object(object_mesh_dir, object_name)
    return HogsSource(
        "h2o",
        root,
        mano_layers_from_dir(mano_dir),
        {object_name: template},
        h2o_mesh_provenance(object_mesh_dir, object_name),
        H2O_VIEWS,
        H2O_EVAL_VIEWS,
    )


def load_run_data(
    cfg: Mapping[str, Any],
    *,
    data: Optional[PathLike] = None,
    mano_dir: Optional[PathLike] = None,
    object_mesh_dir: Optional[PathLike] = None,
    max_eval: Optional[int] = None,
) -> tuple[HogsSource, HogsData]:
    """Reopen a run's dataset and rebuild its split from its ``config.json`` settings.

    Args:
        cfg: the run's ``config.json``.
        data, mano_dir, object_mesh_dir: override the paths stored in it (e.g. on another
            machine).
        max_eval: override the number of held-out samples.
    """
    dataset = cfg.get("dataset", "arctic")
    h2o = dataset == "h2o"
    source = open_hogs_source(
        dataset,
        data or cfg["data"],
        cfg["object"],
        mano_dir=(mano_dir or cfg.get("mano_dir")) if h2o else None,
        object_mesh_dir=(object_mesh_dir or cfg.get("object_mesh_dir")) if h2o else None,
    )
    split = source.load(
        cfg["subject"],
        cfg["object"],
        FrameSelection(
            sequences=cfg.get("sequences"),
            views=cfg.get("views"),
            eval_views=cfg.get("eval_views"),
            eval_every_frame=cfg.get("eval_every_frame", 8),
            frame_stride=cfg.get("frame_stride", 1),
            image_size=cfg.get("image_size"),
            max_eval=cfg.get("max_eval", 8) if max_eval is None else max_eval,
        ),
        masks=cfg.get("masks", "auto"),
        window=cfg.get("window", "crop"),
    )
    return source, split
