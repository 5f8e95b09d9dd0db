"""``nerfmeta eval-geometry``: accuracy, completeness, Chamfer, F-score and normal consistency of a run's surface."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from nerfmeta.config import add_config_options, build_config, given_values
from nerfmeta.geometry.metrics import GeometryConfig


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "eval-geometry",
        help="compare a fitted run's surface with ground truth (Chamfer, F-score, normal consistency); prints JSON",
        description=(
            "Mesh RUN (as 'nerfmeta mesh'), sample both surfaces and report DTU's accuracy and completeness (mean "
            "nearest-neighbour distances below --threshold), Chamfer = their mean, F-score at --tolerance and normal "
            "consistency, in the scene file's units and as %% of the ground truth's bounding-box diagonal, beside the "
            "sampling floor (the Chamfer of two samplings of the ground truth: what a perfect surface scores), the shares "
            "of each surface farther than --threshold (outliers_pred, outliers_gt: what the Chamfer leaves out), the "
            "mesh's topology (components, genus; a surface cut open by the box counts as closed along it) and, "
            "for a generated scene, how much of its hidden concavity (free space inside every view's silhouette, "
            "e.g. a cup's inside) the surface leaves open; for an SDF run, its "
            "signed distance on the true surface (negative: too fat there), overall, on the visual hull (where "
            "silhouettes pin it) and on hidden surface (a cup's inner wall: placed by colour alone), and its mean "
            "|grad f| there (grad_norm: 1 for a signed distance). --gt is a "
            "generated scene (its exact SDF, sampled on the zero level set) or a PLY/OBJ mesh."
        ),
    )
    p.add_argument("run", metavar="RUN", help="a 'nerfmeta fit' run folder")
    p.add_argument("--gt", required=True, metavar="SCENE|MESH", help="generated scene folder or .ply/.obj mesh")
    add_config_options(p, GeometryConfig, flags={"n_points": "--points"})
    p.add_argument("--json-out", default=None, metavar="FILE", help="also write the JSON to FILE (atomically)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nerfmeta.geometry.concavity import concavity_figures, surface_gradient_norm, surface_offsets
    from nerfmeta.geometry.load import load_run_model
    from nerfmeta.geometry.runs import evaluate_mesh, mesh_in_file_frame, topology_summary
    from nerfmeta.geometry.truth import ground_truths, scene_sdf_of
    from nerfmeta.paths import check_output_file, write_output_json

    config = build_config(GeometryConfig, given_values(args, GeometryConfig))
    json_out = check_output_file(args.json_out, option="--json-out", inputs=(args.run, args.gt)) if args.json_out else None
    seeds = (config.seed + 1, config.seed + 2) if config.floor else (config.seed + 1,)
    gt, *rest = ground_truths(args.gt, config.n_points, resolution=max(config.resolution, 128), seeds=seeds)
    twin = rest[0] if rest else None
    model, scene = load_run_model(args.run)
    mesh = mesh_in_file_frame(model, scene, config.resolution, colors=False)
    doc = {**dataclasses.asdict(evaluate_mesh(mesh, gt, config, twin)), "ground_truth": gt.source, "run": args.run,
           "resolution": config.resolution, "topology": topology_summary(mesh)}
    exact = scene_sdf_of(args.gt)
    if exact is not None and scene.alphas is not None:
        doc["concavity"] = dataclasses.asdict(concavity_figures(model, scene, exact[0], seed=config.seed))
    offsets = surface_offsets(model, scene, gt)
    if offsets is not None:
        doc["surface_offset"] = offsets
    grad_norm = surface_gradient_norm(model, scene, gt)
    if grad_norm is not None:
        doc["grad_norm"] = grad_norm
    if json_out is not None:
        write_output_json(json_out, doc, option="--json-out")
    json.dump(doc, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0
