"""The ``img2occ`` stage (``stage._target_module_: renderworld.training.stages.img2occ``).

Importing this package registers :class:`Img2OccStage`. Its modules:

* ``stage``: :class:`Img2OccStage` (training, Occ3D evaluation, report);
* ``builders``: the model config, datasets and trained model of a run (``load_img2occ``);
* ``threshold``: the end-of-training readout threshold selection (a mixin);
* ``export``: the pseudo-label export (``export_pseudo_labels``).
"""

from renderworld.training.stages.img2occ.builders import (
    img2occ_config,
    img2occ_datasets,
    load_img2occ,
)
from renderworld.training.stages.img2occ.stage import MASKS, Img2OccStage, occ3d_report_markdown

__all__ = [
    "Img2OccStage",
    "img2occ_config",
    "img2occ_datasets",
    "load_img2occ",
    "occ3d_report_markdown",
    "MASKS",
]
