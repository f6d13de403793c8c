"""``kpd6d-predict input=IMAGE|FOLDER|VIDEO|CAMERA_INDEX kpd_ckpt=KPD.ckpt detector_ckpt=DET.pt [camera=K_FILE] [track=true] [out_dir=...]``.

Runs :func:`kpd6d.predict.predict_from_config` (settings in conf/predict.yaml): ``poses.json``,
``poses.csv`` and overlays (one PNG per image, or ``overlay.mp4`` for a video) in the run folder.
The camera comes from ``camera``: a BOP ``camera.json``, or a JSON / text file holding a 3x3 matrix;
null -> the LineMod camera. ``track=true`` (with ``track.detect_every`` ...) tracks the objects over
the frames (:mod:`kpd6d.tracking`). Exits with status 1 when an input could not be read.
"""

from __future__ import annotations

import sys

from kpd6d.cli.hydra_app import hydra_main
from kpd6d.predict import IMAGE_EXTS, VIDEO_EXTS, corners_from_kpd, load_intrinsics, predict_inputs  # noqa: F401 (old path)


@hydra_main("predict")
def _app(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    from kpd6d.predict import predict_from_config

    out_dir = cfg.out_dir or HydraConfig.get().runtime.output_dir
    info = predict_from_config(cfg, out_dir)
    print(f"{info['poses']} poses in {info['frames']} frame(s)"
          + (f" ({info['detector_calls']} detector calls)" if "detector_calls" in info else "")
          + f"; wrote {out_dir}/poses.json, poses.csv" + (" and overlays" if cfg.overlays else ""))
    for e in info["errors"]:
        print(f"kpd6d-predict: skipped {e['name']}: {e['error']}", file=sys.stderr)
    if info["errors"]:
        print(f"kpd6d-predict: {len(info['errors'])} input(s) failed (listed in {out_dir}/poses.json 'errors')",
              file=sys.stderr)
        sys.exit(1)


def main() -> None:
    """``kpd6d-predict``: ``track=true|false`` becomes ``track.enabled=...`` (``track`` is a settings node)."""
    from kpd6d.predict import expand_track_override

    sys.argv[1:] = expand_track_override(sys.argv[1:])
    _app()


if __name__ == "__main__":
    main()
