"""``kpd6d-evaluate data.root=... kpd_ckpt=KPD.ckpt [detector_ckpt=oracle|DET.pt] [pnp=epnp|epnp_ransac|...] [select.top_l=10]``.

Runs :func:`kpd6d.workflow.run_evaluation` (configs in conf/evaluate.yaml), which writes
metrics.json, results.csv, report.md, plots and overlays into the run folder.

In shards (docs/scale-out.md): ``kpd6d-evaluate -m ... out_dir=DIR shard=0,1 num_shards=2`` predicts
each shard's frames into ``DIR/shards/``; then ``kpd6d-evaluate ... out_dir=DIR num_shards=2
merge=true`` writes the single job's outputs from them.
"""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main
from kpd6d.workflow import run_evaluation


@hydra_main("evaluate")
def main(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    sharded = int(cfg.get("num_shards", 1)) > 1 or bool(cfg.get("merge", False))
    if sharded and not cfg.out_dir:
        raise SystemExit("error: kpd6d-evaluate with num_shards > 1 or merge=true needs out_dir=<folder>, the same "
                         "for every shard and the merge (the Hydra run folder differs from job to job)")
    out_dir = cfg.out_dir or HydraConfig.get().runtime.output_dir
    m = run_evaluation(cfg, out_dir)
    if "mean" not in m:  # one shard
        print(f"kpd6d-evaluate: shard {m['shard']} of {m['num_shards']}: predictions of {m['frames']} frames in "
              f"{m['out_dir']}; when every shard has finished, rerun with num_shards={m['num_shards']} merge=true")
        return
    mean = m["mean"]
    print(f"ADD(-S) 0.1d {100 * mean['add_s_01d']:.1f} %  2D proj 5px {100 * mean['proj2d_5px']:.1f} %  "
          f"AR_MSSD {100 * mean.get('ar_mssd', float('nan')):.1f} %  AR_MSPD {100 * mean.get('ar_mspd', float('nan')):.1f} %  "
          f"fps {m['fps'] or 0:.2f}")
    print(f"wrote {out_dir}/report.md")


if __name__ == "__main__":
    main()
