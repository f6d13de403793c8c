"""``kpd6d-generate out_dir=... [num_images=...] [options.KEY=...]``: write a synthetic BOP dataset
(Hydra; settings in conf/generate.yaml, the same as :func:`kpd6d.synth.generate_dataset`)."""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main


def run(cfg) -> str:
    """Call :func:`~kpd6d.synth.generate_dataset` with a generate.yaml config; returns the root."""
    from omegaconf import OmegaConf

    from kpd6d.synth import generate_dataset

    c = OmegaConf.to_container(cfg, resolve=True)
    c.pop("hydra", None)
    options = c.pop("options", {}) or {}
    top = ("out_dir", "models_dir", "obj_ids", "num_images", "split", "seed", "workers", "progress")
    unknown = sorted(set(c) - set(top))
    if unknown:
        raise TypeError(f"kpd6d-generate: unknown top-level setting(s) {unknown}; generator options go under options.")
    return str(generate_dataset(c.pop("out_dir"), **{k: c[k] for k in top[1:] if k in c}, **options))


@hydra_main("generate")
def main(cfg) -> None:
    print(f"kpd6d-generate: dataset written to {run(cfg)}")


if __name__ == "__main__":
    main()
