"""``kpd6d-run [experiment=demo|linemod|occlusion] [overrides...]``: the whole method end to end.

Designates keypoints, generates data, trains the detector and the KPD, evaluates and writes the
report into the run folder (see :mod:`kpd6d.workflow` and conf/run.yaml). Rerunning with the same
``hydra.run.dir`` resumes an interrupted run.
"""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main


def summarize(metrics: dict, run_dir) -> str:
    from kpd6d.workflow import yardstick_line

    mean = metrics["mean"]
    t = metrics.get("run", {}).get("timings", {})
    return (f"ADD(-S) 0.1d {100 * mean['add_s_01d']:.1f} %   2D projection 5px {100 * mean['proj2d_5px']:.1f} %   "
            f"AR_MSSD {100 * mean.get('ar_mssd', float('nan')):.1f} %   AR_MSPD {100 * mean.get('ar_mspd', float('nan')):.1f} %"
            f"   ({t.get('total_s', 0) / 60:.1f} min)\nreport: {run_dir}/eval/report.md"
            + "".join(f"\n{yardstick_line(name, entry)}" for name, entry in metrics.get("yardsticks", {}).items()))


@hydra_main("run")
def main(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    from kpd6d.workflow import run_experiment

    run_dir = HydraConfig.get().runtime.output_dir
    print(summarize(run_experiment(cfg, run_dir), run_dir))


if __name__ == "__main__":
    main()
