"""``nerfmeta classify``: name a scene's category, or answer that it is unknown, as JSON."""

from __future__ import annotations

import argparse
import json
import sys

from classifier.config import SCORES
from nerfmeta.data.video import is_video


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "classify",
        help="classify a scene (or images) with a trained classifier; prints JSON",
        description=(
            "Classify SCENE from all of its views (every split): softmax per view, averaged over the views, "
            "plus the unknown-category decision calibrated when the classifier was trained. SCENE is a scene "
            "folder in any supported format, a folder of PNG, JPEG or HEIC images, one image, or a video (its "
            "frames as 'fit VIDEO' keeps them); any size, RGB or RGBA (composited on the classifier's training "
            "background), 8- or 16-bit PNG, JPEG. Prints "
            '{"category", "confidence", "unknown", "probabilities", "views", "score"} on stdout.'
        ),
    )
    p.add_argument("scene", metavar="SCENE", help="scene folder, .npz scene, image folder or image file")
    p.add_argument("--classifier", default=None, metavar="DIR",
                   help="classifier folder from 'nerfmeta classifier train' (default: the model zoo's classifier, see --zoo)")
    p.add_argument("--zoo", default=None, metavar="DIR",
                   help="model zoo whose classifier answers when --classifier is not given (default: $NERFMETA_ZOO, else "
                        "the model_zoo/ shipped with nerfmeta; 'none': no zoo)")
    p.add_argument("--json-out", default=None, metavar="FILE", help="also write the JSON to FILE (atomically)")
    p.add_argument("--score", default=None, metavar="NAME",
                   help=f"decide with another score the classifier calibrated ({', '.join(SCORES)}; default: the one it chose)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from classifier.inputs import read_scene_views
    from classifier.store import classify_views, load_classifier
    from nerfmeta.paths import check_output_file, write_output_json

    folder, zoo_root = (args.classifier, None) if args.classifier is not None else zoo_classifier(args.zoo)
    json_out = (check_output_file(args.json_out, option="--json-out", inputs=(args.scene, folder, zoo_root))
                if args.json_out else None)  # before the classifier loads; never replaces a file of the inputs (or their zoo)
    classifier = load_classifier(folder, device=args.device)
    if args.score is not None:
        classifier = classifier.with_score(args.score)
    meta = classifier.meta
    scene = args.scene
    if is_video(scene):  # a phone video: its frames, as 'fit VIDEO' takes them (cached)
        from nerfmeta.commands.poses import frames_of_video

        scene = frames_of_video(scene)
    views = read_scene_views(scene, size=meta.input_size, background=meta.background)
    doc = classify_views(classifier, views).to_json()
    if json_out is not None:
        write_output_json(json_out, doc, option="--json-out")
    json.dump(doc, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


def zoo_classifier(zoo: str | None) -> tuple[str | None, str | None]:
    """(classifier folder, zoo folder) of the zoo :func:`nerfmeta.zoo.open_zoo` picks (hash-checked), each None when
    there is none; says which."""
    from nerfmeta.zoo import open_zoo

    found = open_zoo(zoo)
    entry = None if found is None else found.classifier
    if entry is None:
        return None, None
    print(f"nerfmeta classify: the model zoo's classifier ({entry.path})", file=sys.stderr)
    return str(entry.path), str(found.root)
