"""``kpd6d-designate [models_dir=...] [out_dir=...] [designator=sift|fps|bbox_corners] [designator.KEY=...]``:
designate keypoints for every object of a BOP models folder (or the procedural set), cache them in a
keypoint JSON file and draw one overview PNG per object (Hydra; settings in conf/designate.yaml;
the work is :func:`kpd6d.keypoints.designate.designate_from_config`)."""

from __future__ import annotations

from pathlib import Path

from kpd6d.cli.hydra_app import hydra_main


def run(cfg) -> Path:
    """Designate with a designate.yaml config; returns the keypoint JSON path."""
    from kpd6d.keypoints.designate import designate_from_config

    cache, points, reused = designate_from_config(cfg)
    print(f"kpd6d-designate: {len(points)} object(s) ({len(reused)} from the cache) -> {cache}")
    return cache


@hydra_main("designate")
def main(cfg) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
