"""``kpd6d-designate [models_dir=...] [out_dir=...] [designator=sift|fps|bbox_corners] [designator.KEY=...]``:
designate keypoints for every object of a BOP models folder (or the procedural set), cache them in a
keypoint JSON file and draw one overview PNG per object (Hydra; settings in conf/designate.yaml)."""

from __future__ import annotations

from pathlib import Path

from kpd6d.cli.hydra_app import hydra_main


def run(cfg) -> Path:
    """Designate with a designate.yaml config; returns the keypoint JSON path."""
    from omegaconf import OmegaConf
    from tqdm.auto import tqdm

    from kpd6d.data import atomic_write_image
    from kpd6d.keypoints.designate import designate_objects, render_overview
    from kpd6d.objects import load_bop_models, procedural_objects

    c = OmegaConf.to_container(cfg, resolve=True)
    c.pop("hydra", None)
    known = {"designator", "out_dir", "cache_name", "models_dir", "obj_ids", "procedural_seed", "overview", "progress"}
    unknown = sorted(set(c) - known)
    if unknown:
        raise TypeError(f"kpd6d-designate: unknown setting(s) {unknown}; known: {sorted(known)}")
    des = dict(c["designator"] or {})
    if "name" not in des:
        raise KeyError(f"kpd6d-designate: the designator config has no 'name' (got keys {sorted(des)})")
    name = des.pop("name")
    obj_ids = c.get("obj_ids")
    if c.get("models_dir"):
        models = load_bop_models(c["models_dir"], obj_ids=obj_ids)
    else:
        models = procedural_objects(seed=int(c.get("procedural_seed", 0)), obj_ids=obj_ids)
    out_dir = Path(c["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / c.get("cache_name", "keypoints.json")
    progress = bool(c.get("progress", True))
    points, reused = designate_objects(models, name, des, cache, progress=progress)
    ov = c.get("overview") or {}
    if ov.get("enabled", True):
        from kpd6d.render import Renderer

        size = int(ov.get("image_size", 320))
        renderer = Renderer(size, size)  # one OpenGL context for all objects (K is set per object)
        try:
            for m in tqdm(models, desc="overview PNGs", unit="object", disable=not progress):
                title = f"obj {m.obj_id} {m.name}: {len(points[m.obj_id])} {name} keypoints"
                img = render_overview(m, points[m.obj_id], num_views=int(ov.get("num_views", 6)),
                                      image_size=size, title=title, renderer=renderer)
                atomic_write_image(out_dir / f"obj_{m.obj_id:06d}.png", img)
        finally:
            renderer.close()
    print(f"kpd6d-designate: {len(points)} object(s) ({len(reused)} from the cache) -> {cache}")
    return cache


@hydra_main("designate")
def main(cfg) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
