"""Synthetic training data: render-and-paste images of object models written as BOP datasets.

``generate_dataset(out_dir, models_dir=None, ...)`` is the entry point (CLI: ``kpd6d-generate``);
:mod:`~kpd6d.synth.poses` samples poses, :mod:`~kpd6d.synth.backgrounds` makes backgrounds,
:mod:`~kpd6d.synth.distractors` makes occluders, :mod:`~kpd6d.synth.scene` composes one image
(:mod:`~kpd6d.synth.tabletop`: the table, camera and resting poses of ``layout: tabletop``),
:mod:`~kpd6d.synth.photometric` applies blur / noise / colour shifts. BOP files are written through
:mod:`kpd6d.data`; :mod:`~kpd6d.synth.prepare` is the one data-preparation path of the workflow and the
training stages; :mod:`~kpd6d.synth.shards` merges a split generated in shards (``shard=i, num_shards=n``).
"""

from kpd6d.synth.config import SynthConfig, default_K
from kpd6d.synth.generate import generate_dataset, image_rng
from kpd6d.synth.prepare import generate_splits, prepare_data
from kpd6d.synth.shards import ShardMergeError, merge_shards

__all__ = ["ShardMergeError", "SynthConfig", "default_K", "generate_dataset", "generate_splits", "image_rng",
           "merge_shards", "prepare_data"]
