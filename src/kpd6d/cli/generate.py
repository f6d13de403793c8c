"""``kpd6d-generate out_dir=... [num_images=...] [options.KEY=...]``: write a synthetic BOP dataset
(Hydra; settings in conf/generate.yaml, the same as :func:`kpd6d.synth.generate_dataset`).

In shards (docs/scale-out.md): ``kpd6d-generate -m ... shard=0,1,2 num_shards=3`` makes the three
shards (in parallel with ``hydra/launcher=local_parallel``), then ``kpd6d-generate out_dir=...
num_shards=3 merge=true`` checks them and writes the final scene files (:func:`kpd6d.synth.merge_shards`).
"""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main

TOP = ("out_dir", "models_dir", "obj_ids", "num_images", "split", "seed", "workers", "progress", "shard", "num_shards")


def run(cfg) -> str:
    """Call :func:`~kpd6d.synth.generate_dataset` (or, with ``merge=true``,
    :func:`~kpd6d.synth.merge_shards`) with a generate.yaml config; returns the root."""
    from omegaconf import OmegaConf

    from kpd6d.synth import generate_dataset, merge_shards

    c = OmegaConf.to_container(cfg, resolve=True)
    c.pop("hydra", None)
    options = c.pop("options", {}) or {}
    merge = bool(c.pop("merge", False))
    unknown = sorted(set(c) - set(TOP))
    if unknown:
        raise TypeError(f"kpd6d-generate: unknown top-level setting(s) {unknown}; generator options go under options.")
    if merge:
        if int(c.get("num_shards", 1)) < 2:
            raise ValueError("kpd6d-generate merge=true: give num_shards=<n>, the number of shards the split was "
                             "generated in")
        merge_shards(c["out_dir"], c.get("split", "train"), c["num_shards"])
        return str(c["out_dir"])
    return str(generate_dataset(c.pop("out_dir"), **{k: c[k] for k in TOP[1:] if k in c}, **options))


@hydra_main("generate")
def main(cfg) -> None:
    root = run(cfg)
    if cfg.get("merge"):
        print(f"kpd6d-generate: {cfg.num_shards} shards of {root}/{cfg.split} merged")
    elif int(cfg.get("num_shards", 1)) > 1:
        print(f"kpd6d-generate: shard {cfg.shard} of {cfg.num_shards} written to {root}; when every shard has "
              f"finished: kpd6d-generate out_dir={root} split={cfg.split} num_shards={cfg.num_shards} merge=true")
    else:
        print(f"kpd6d-generate: dataset written to {root}")


if __name__ == "__main__":
    main()
