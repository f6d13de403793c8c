"""``kpd6d-evaluate data.root=... kpd_ckpt=KPD.ckpt [detector_ckpt=oracle|DET.pt] [pnp=epnp|epnp_ransac|...] [select.top_l=10]``.

Runs :func:`kpd6d.evaluation.evaluate.evaluate` (configs in conf/evaluate.yaml) and writes
metrics.json, results.csv, report.md, plots and overlays into the run folder.
"""

from __future__ import annotations

from pathlib import Path

from kpd6d.cli.hydra_app import hydra_main


def run_evaluation(cfg, out_dir: str | Path, extra_metrics: dict | None = None) -> dict:
    """The work of ``kpd6d-evaluate`` for a composed config (callable without Hydra's runtime)."""
    from omegaconf import OmegaConf

    from kpd6d.data import BopDataset
    from kpd6d.evaluation.evaluate import evaluate
    from kpd6d.pipeline import PosePipeline

    root = Path(cfg.data.root)
    if not root.is_dir():
        raise FileNotFoundError(f"data.root={str(root)!r}: BOP dataset root does not exist")
    targets = cfg.data.targets
    if targets == "auto":
        targets = "test_targets_bop19.json" if (root / "test_targets_bop19.json").is_file() else None
    pnp_cfg = OmegaConf.to_container(cfg.pnp, resolve=True)
    top_l = cfg.select.top_l
    obj_ids = list(cfg.data.obj_ids) if cfg.data.obj_ids else None
    pipeline = PosePipeline.from_checkpoints(cfg.detector_ckpt, cfg.kpd_ckpt, pnp=pnp_cfg, top_l=top_l,
                                             device=cfg.device, obj_ids=obj_ids,
                                             refine_boxes=int(cfg.get("refine_boxes", 0) or 0))
    covered = sorted(int(o) for o in pipeline.kpd.keypoints_3d)
    wanted = obj_ids if obj_ids is not None else covered
    missing = sorted(set(wanted) - set(covered))
    if missing:
        raise ValueError(f"data.obj_ids {missing} are not covered by the KPD checkpoint {cfg.kpd_ckpt} (it covers {covered})")
    ds = BopDataset(root, cfg.data.split, obj_ids=wanted, targets=targets)
    info = {"targets": targets, "detector": str(cfg.detector_ckpt), "kpd": str(cfg.kpd_ckpt), "pnp": pnp_cfg,
            "top_l": top_l, "refine_boxes": pipeline.refine_boxes, "device": str(pipeline.device)}
    return evaluate(pipeline, ds, out_dir, oracle=str(cfg.detector_ckpt) == "oracle", batch_size=int(cfg.batch_size),
                    max_frames=cfg.data.max_frames, n_overlays=int(cfg.overlays), run_info=info,
                    progress=bool(cfg.progress), extra_metrics=extra_metrics)


@hydra_main("evaluate")
def main(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    out_dir = cfg.out_dir or HydraConfig.get().runtime.output_dir
    m = run_evaluation(cfg, out_dir)
    mean = m["mean"]
    print(f"ADD(-S) 0.1d {100 * mean['add_s_01d']:.1f} %  2D proj 5px {100 * mean['proj2d_5px']:.1f} %  "
          f"AR_MSSD {100 * mean.get('ar_mssd', float('nan')):.1f} %  AR_MSPD {100 * mean.get('ar_mspd', float('nan')):.1f} %  "
          f"fps {m['fps'] or 0:.2f}")
    print(f"wrote {out_dir}/report.md")


if __name__ == "__main__":
    main()
