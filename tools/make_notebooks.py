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
    ("md", "# kpd6d pipeline on a tiny synthetic dataset\n\nGenerate a few render-and-paste images of a procedural "
           "object, run the pose pipeline (oracle boxes, a KPD stand-in that reads the ground truth, so this notebook "
           "runs in seconds without training), draw poses and plot accuracy curves. With trained checkpoints, "
           "`PosePipeline.from_checkpoints(detector_ckpt, kpd_ckpt)` replaces the stand-ins."),
    ("code", "import tempfile\nfrom pathlib import Path\nimport numpy as np\n"
             "import matplotlib.pyplot as plt\n\nfrom kpd6d.synth import generate_dataset\nfrom kpd6d.data import BopDataset\n"
             "root = Path(tempfile.mkdtemp()) / 'tiny'\n"
             "generate_dataset(root, obj_ids=[1], num_images=6, split='test', seed=3, workers=1, width=320, height=240,\n"
             "                 designator={'name': 'fps', 'num_keypoints': 12}, progress=False)\n"
             "ds = BopDataset(root, split='test')\nprint(len(ds), 'frames;', ds[0].instances[0])"),
]


def build(cells):
    nb = new_notebook()
    nb.cells = [new_markdown_cell(src) if kind == "md" else new_code_cell(src) for kind, src in cells]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    return nb


if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "notebooks"
    out.mkdir(exist_ok=True)
    nbformat.write(build(NB01), out / "01_registries.ipynb")
    print("wrote", out / "01_registries.ipynb")
