"""Which pixels are which: class labels for the stages that learn or measure by region (material recognition, the
vein's contrast, a material's scattering profile).

A capture of the simulated rig labels itself (``labels: scene``: the objects of the scene it records, by name, the
background unlabelled); any other capture takes an integer label image (``labels: image``: .npy, a member of an .npz
named ``file.npz:member``, PNG or TIFF of the frame's size, 0 unlabelled, codes 1 … n named by the stage's
``classes``).
"""

from __future__ import annotations

import os
from typing import Literal

import numpy as np
import xarray as xr

from selpath.pipeline.errors import Problem, StageError
from selpath.stages._common import file_identity

#: where the truth comes from: the simulated scene's objects, or a label image file
Labels = Literal["scene", "image"]


def label_map(profiles: xr.Dataset, labels: str, image: str, classes: tuple[str, ...] | None,
              where: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """Integer codes over (row, col) (0: unlabelled, k: ``classes[k − 1]``) and the class names.

    ``labels`` is ``scene`` (the objects of the simulated scene the capture was rendered from, named as in the
    scene file; the background unlabelled) or ``image``: ``image`` is then the path of an integer image (.npy, or
    PNG/TIFF) of the frame's size, whose codes 1 … n ``classes`` names.
    """
    shape = (profiles.sizes["row"], profiles.sizes["col"])
    labels, image = (image, "") if labels == "image" else (labels, image)
    if labels == "scene":
        from selpath.stages.procam._scene_truth import scene_labels

        codes, names = scene_labels(profiles, where)
        if codes.shape != shape:
            raise StageError(Problem(f"the scene renders {codes.shape}, the profiles are {shape}", where=where))
    else:
        file, member = label_file(labels)
        if not labels or not os.path.exists(file):
            raise StageError(Problem(f"no label image at {labels!r}", where=where,
                                     fix="give an integer image (.npy, .npz:member, .png, .tif) of codes 1 … n, 0 "
                                         "unlabelled"))
        if member:
            with np.load(file, allow_pickle=False) as archive:
                if member not in archive.files:
                    raise StageError(Problem(f"{file} has no member {member!r}; it holds {archive.files}",
                                             where=where))
                codes = archive[member]
        elif labels.endswith(".npy"):
            codes = np.load(labels, allow_pickle=False)
        else:
            import imageio.v3 as iio

            codes = iio.imread(labels)
        if codes.shape != shape or not np.issubdtype(codes.dtype, np.integer):
            raise StageError(Problem(f"the label image {labels} is {codes.dtype} {codes.shape}; the profiles are "
                                     f"{shape}: labels must be integer codes of the same size", where=where))
        if not classes:
            raise StageError(Problem(f"the label image {labels} has codes but no class names", where=where,
                                     fix="give classes: the names of codes 1, 2, …"))
        names = tuple(classes)
        if codes.min() < 0 or codes.max() > len(names):
            raise StageError(Problem(f"the label image {labels} has codes {int(codes.min())} … {int(codes.max())}; "
                                     f"classes names {len(names)} (codes 1 … {len(names)}, 0 unlabelled)",
                                     where=where))
    if not (codes > 0).any():
        raise StageError(Problem("no pixel is labelled", where=where,
                                 fix="label some pixels of each material with its code (0 is unlabelled)"))
    return codes.astype(np.int16), names


def label_file(label_image: str) -> tuple[str, str]:
    """(the file, the .npz member or "") a label image setting names: ``labels.npz:member`` or a path.

    >>> label_file("dev/D1.npz:labels"), label_file("codes.png")
    (('dev/D1.npz', 'labels'), ('codes.png', ''))
    """
    file, _, member = label_image.partition(".npz:")
    return (file + ".npz", member) if member else (label_image, "")


def label_precheck(settings) -> list[str]:
    """A stage's ``labels: image`` without a label image file, at validation time."""
    if settings.labels == "image" and not os.path.isfile(label_file(settings.label_image)[0]):
        return [f"labels: image needs label_image, an integer label image; {settings.label_image!r} is not a file"]
    return []


def label_identity(settings) -> dict:
    """What a stage's labels are, for provenance: the label image by content, else where they come from."""
    if settings.labels != "image":
        return {"labels": settings.labels}
    file, member = label_file(settings.label_image)
    return file_identity(file) | ({"member": member} if member else {})
