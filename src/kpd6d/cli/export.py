"""``kpd6d-export kpd_ckpt=KPD.ckpt detector_ckpt=DET.pt|oracle [out_dir=...] [opset=17]``.

Runs :func:`kpd6d.deploy.export.export_models` (settings in conf/export.yaml): ``kpd.onnx``,
``detector.onnx`` and the ``kpd6d_export.json`` sidecar in the run folder; run them with
``kpd6d-predict backend=onnxruntime export_dir=...`` (docs/deployment.md).
"""

from __future__ import annotations

from kpd6d.cli.hydra_app import hydra_main


@hydra_main("export")
def main(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    from kpd6d.deploy.export import export_models

    out_dir = cfg.out_dir or HydraConfig.get().runtime.output_dir
    side = export_models(cfg.kpd_ckpt, cfg.detector_ckpt, out_dir, opset=int(cfg.opset), check=bool(cfg.check))
    print(f"exported KPD ({len(side['kpd']['obj_ids'])} objects) and detector ({side['detector']['name']}) "
          f"to {out_dir} (opset {side['opset']})")


if __name__ == "__main__":
    main()
