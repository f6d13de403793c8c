"""``kpd6d-evaluate data.root=... kpd_ckpt=KPD.ckpt [detector_ckpt=oracle|DET.pt] [pnp=epnp|epnp_ransac|...] [select.top_l=10]``.

Runs :func:`kpd6d.workflow.run_evaluation` (configs in conf/evaluate.yaml), which writes
metrics.json, results.csv, report.md, plots and overlays into the run folder.
"""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main
from kpd6d.workflow import run_evaluation


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
