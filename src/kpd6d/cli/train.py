"""``kpd6d-train stage=kpd|detector ...``: train one stage (Hydra; configs in conf/train.yaml)."""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main


@hydra_main("train")
def main(cfg) -> None:
    stage = cfg.stage.name
    if stage == "kpd":
        from kpd6d.kpd.train import train_kpd

        train_kpd(cfg)
    elif stage == "detector":
        from kpd6d.detection.train import train_detector

        train_detector(cfg)
    else:  # pragma: no cover - Hydra's config group already restricts the choice
        raise ValueError(f"unknown stage {stage!r}; known stages: kpd, detector")


if __name__ == "__main__":
    main()
