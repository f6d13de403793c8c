"""Write notebooks/*.ipynb from the cell sources below (outputs stripped). Run: python tools/make_notebooks.py"""

from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

NB01 = [
    ("md", "# kpd6d registries and keypoint designation\n\nEvery pluggable part of kpd6d lives in a registry "
           "(`kpd6d.registry`); each Hydra config group in `conf/` names one entry. This notebook lists "
           "and builds entries, designates keypoints on a procedural object with the three designators, "
           "and compares them."),
    ("code", "import numpy as np\nimport matplotlib.pyplot as plt\n\n"
             "from kpd6d.registry import REGISTRIES, DESIGNATORS, PNP_SOLVERS, SYMMETRIES\n"
             "for group, reg in REGISTRIES.items():\n    print(f'{group:10s} ({reg.kind}): {reg.names()}')"),
    ("md", "An unknown name is an error that lists the known ones:"),
    ("code", "try:\n    PNP_SOLVERS.build('p3p_magic')\nexcept KeyError as exc:\n    print(exc)"),
    ("md", "## A PnP solver from the registry\nRecover a pose from exact correspondences (points in mm, LineMod camera)."),
    ("code", "from kpd6d.geometry import LINEMOD_K, pose_from_view, project_points, rotation_error_deg\n"
             "rng = np.random.default_rng(0)\nX = rng.uniform(-60, 60, (20, 3))\n"
             "R, t = pose_from_view(0.4, 0.6, 700.0, inplane=0.2)\nuv = project_points(X, LINEMOD_K, R, t)\n"
             "est = PNP_SOLVERS.build('epnp')(X, uv, LINEMOD_K)\n"
             "print(est.ok, 'rotation error (deg):', float(rotation_error_deg(est.R, R)), "
             "'translation error (mm):', float(np.linalg.norm(est.t - t)))\nassert est.ok"),
    ("md", "## Procedural objects\nThe library's embedded default: textured meshes made in code "
           "(no data files). Their symmetries are known by construction, and `auto` finds them from the mesh."),
    ("code", "from kpd6d.objects import procedural_objects\nobjects = procedural_objects()\n"
             "auto = SYMMETRIES.build('auto')\nfor m in objects:\n"
             "    found = auto(m)\n"
             "    print(f'{m.obj_id} {m.name:7s} diameter {m.diameter:6.1f} mm  declared sym: '\n"
             "          f'{len(m.symmetries_discrete)} discrete, {len(m.symmetries_continuous)} continuous; '\n"
             "          f'auto: {len(found[\"symmetries_discrete\"])} discrete, {len(found[\"symmetries_continuous\"])} continuous')"),
    ("md", "## Designate keypoints\n`DESIGNATORS.build(name, num_keypoints=k, **params)(model) -> (k, 3)` in the model frame (mm). "
           "`sift` renders the object from many views and keeps repeatable SIFT points (fewer views here, for speed)."),
    ("code", "model = objects[0]\n"
             "designators = {\n"
             "    'sift': DESIGNATORS.build('sift', num_keypoints=20, num_views=24),\n"
             "    'bbox_corners': DESIGNATORS.build('bbox_corners', num_keypoints=9),\n"
             "    'fps': DESIGNATORS.build('fps', num_keypoints=20),\n}\n"
             "keypoints = {name: d(model) for name, d in designators.items()}\n"
             "for name, kp in keypoints.items():\n    print(name, kp.shape)"),
    ("md", "Drawn over a render (front-facing keypoints filled, back-face ones hollow):"),
    ("code", "from kpd6d.render import Renderer\nrenderer = Renderer(320, 240, LINEMOD_K * [[0.5], [0.5], [1]])\n"
             "R, t = pose_from_view(0.8, 0.5, 330.0)\nres = renderer.render([(model, R, t)])\n"
             "fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))\n"
             "for ax, (name, kp) in zip(axes, keypoints.items()):\n"
             "    uv, z = project_points(kp, renderer.K, R, t, return_depth=True)\n"
             "    px = np.clip(np.round(uv).astype(int), 0, [319, 239])\n"
             "    front = np.abs(res.depth[px[:, 1], px[:, 0]] - z) < 0.02 * model.diameter\n"
             "    ax.imshow(res.rgb)\n"
             "    ax.scatter(uv[front, 0], uv[front, 1], c='yellow', edgecolors='k', s=30)\n"
             "    ax.scatter(uv[~front, 0], uv[~front, 1], facecolors='none', edgecolors='yellow', s=30)\n"
             "    ax.set_title(name)\n    ax.axis('off')\nfig.tight_layout()"),
    ("md", "## Compare designators\nSpread (smallest pairwise distance relative to the diameter) and distance to the surface."),
    ("code", "import trimesh\nfor name, kp in keypoints.items():\n"
             "    d = np.linalg.norm(kp[:, None] - kp[None], axis=-1) + np.eye(len(kp)) * 1e9\n"
             "    _, surf, _ = trimesh.proximity.closest_point(model.mesh, kp)\n"
             "    print(f'{name:13s} k={len(kp):2d}  min pairwise {d.min() / model.diameter:.3f} d  '\n"
             "          f'max distance to surface {surf.max():6.2f} mm')"),
]

NB02 = [
    ("md", "# kpd6d pipeline on a tiny synthetic dataset\n\n"
           "Generate a few render-and-paste images of a procedural object, train a small keypoint detector "
           "briefly, run the pose pipeline with ground-truth boxes (the `oracle` detector), draw poses and "
           "plot accuracy curves. A model trained this briefly is inaccurate; set `KPD6D_KPD_CKPT` to a trained "
           "checkpoint (e.g. from `make demo`: `outputs/demo/<date>/kpd/checkpoints/best.ckpt`) to use it instead."),
    ("code", "import os\nimport tempfile\nfrom pathlib import Path\nimport numpy as np\nimport matplotlib.pyplot as plt\n\n"
             "from kpd6d.synth import generate_dataset\nfrom kpd6d.data import BopDataset\n\n"
             "work = Path(tempfile.mkdtemp())\nroot = work / 'tiny'\n"
             "common = dict(obj_ids=[1], workers=1, progress=False, width=320, height=240,\n"
             "              designator={'name': 'fps', 'num_keypoints': 12})\n"
             "for split, n, seed in [('train', 48, 1), ('val', 8, 2), ('test', 8, 3)]:\n"
             "    generate_dataset(root, num_images=n, split=split, seed=seed, **common)\n"
             "test = BopDataset(root, split='test')\n"
             "print(len(test), 'test frames; first instance:', test[0].instances[0].obj_id, test[0].instances[0].t)"),
    ("md", "A generated frame with its ground-truth pose (3D box, axes) and keypoints drawn over it:"),
    ("code", "from kpd6d.synth.preview import draw_frame\n"
             "models = {m.obj_id: m for m in test.load_models()}\n"
             "plt.figure(figsize=(5, 4))\nplt.imshow(draw_frame(test[0], models, test.load_keypoints()))\nplt.axis('off');"),
    ("md", "## Train a keypoint detector (briefly) through the same config as `kpd6d-train stage=kpd`"),
    ("code", "from hydra import compose, initialize_config_dir\nfrom kpd6d.config import config_dir\n"
             "from kpd6d.kpd.train import train_kpd\n\n"
             "kpd_ckpt = os.environ.get('KPD6D_KPD_CKPT')\n"
             "if not kpd_ckpt:\n"
             "    with initialize_config_dir(config_dir=str(config_dir()), version_base='1.3'):\n"
             "        cfg = compose('train', overrides=[\n"
             "            'stage=kpd', 'kpd@stage.kpd=cpu_small', 'backbone@stage.backbone=resnet18',\n"
             "            f'data.root={root}', f'+run_dir={work / \"kpd\"}', 'stage.kpd.num_workers=0',\n"
             "            'stage.kpd.trainer.max_epochs=2', 'stage.kpd.trainer.max_time=null'])\n"
             "    run_dir = train_kpd(cfg)\n"
             "    kpd_ckpt = str(Path(run_dir) / 'checkpoints' / 'last.ckpt')\n"
             "print('KPD checkpoint:', kpd_ckpt)"),
    ("md", "## Run the pipeline: oracle boxes → crop → KPD → decode → top-l → EPnP"),
    ("code", "from kpd6d.pipeline import PosePipeline\n"
             "pipe = PosePipeline.from_checkpoints('oracle', kpd_ckpt, pnp='epnp', top_l=None, device='cpu')\n"
             "frame = test[0]\n"
             "targets = {'boxes': np.array([i.bbox_visib for i in frame.instances], dtype=np.float32),\n"
             "           'obj_ids': np.array([i.obj_id for i in frame.instances])}\n"
             "poses = pipe(frame.load_rgb(), frame.K, targets=targets)\n"
             "for p in poses:\n"
             "    print(p['obj_id'], 'ok' if p['ok'] else p['reason'], 't =', np.round(p['t'], 1), "
             "' (GT', np.round(frame.instances[0].t, 1), ')')"),
    ("md", "Ground truth (green) and prediction (blue):"),
    ("code", "from kpd6d.visualize import draw_overlay\n"
             "corners = {o: m.bbox_corners for o, m in models.items()}\n"
             "img = draw_overlay(frame.load_rgb(), frame.K, corners, [(i.obj_id, i.R, i.t) for i in frame.instances],\n"
             "                   [(p['obj_id'], p['R'], p['t']) for p in poses if p['ok']])\n"
             "plt.figure(figsize=(5, 4))\nplt.imshow(img)\nplt.axis('off');"),
    ("md", "## Evaluate on the test split and plot accuracy–threshold curves"),
    ("code", "from kpd6d.evaluation.runner import evaluate\n"
             "metrics = evaluate(pipe, test, work / 'eval', oracle=True, batch_size=4, progress=False)\n"
             "print({k: round(v, 3) for k, v in metrics['mean'].items() if isinstance(v, float)})\n"
             "fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))\n"
             "for ax, key, label in [(axes[0], 'proj2d', 'pixel threshold'), (axes[1], 'add_s', 'ADD(-S) threshold (× diameter)')]:\n"
             "    ax.plot(metrics['curves'][key + '_thresholds'], np.array(metrics['mean']['curves'][key]) * 100)\n"
             "    ax.set_xlabel(label)\n"
             "    ax.set_ylabel('accuracy (%)')\n"
             "    ax.grid(alpha=0.3)"),
]


def build(cells):
    nb = new_notebook()
    nb.cells = [new_markdown_cell(src) if kind == "md" else new_code_cell(src) for kind, src in cells]
    for i, cell in enumerate(nb.cells):  # stable ids: regenerating gives the same file
        cell["id"] = f"cell-{i:02d}"
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    return nb


if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "notebooks"
    out.mkdir(exist_ok=True)
    for name, cells in (("01_registries.ipynb", NB01), ("02_pipeline.ipynb", NB02)):
        nbformat.write(build(cells), out / name)
        print("wrote", out / name)
