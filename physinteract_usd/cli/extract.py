"""`physinteract-usd extract`: find the hand's contact, timing, type, supports and initial trajectory (the verb: `physinteract_usd.app.extract`)."""

from __future__ import annotations

import json

from .common import progress_log


def add_parser(sub):
    s = sub.add_parser("extract", help="find the hand's contact, timing, type, supports and initial trajectory")
    s.add_argument("stage")
    s.add_argument("--type", choices=["pointAdherent", "pointNonAdherent", "surfaceNonAdherent"],
                   help="the interaction type (overrides detection)")
    s.add_argument("--hint-pixel", metavar="K,U,V", help="the contact is at pixel column U, row V of frame K")
    s.add_argument("--hint-particles", metavar="I,J,...", help="the contact holds these particles")
    s.add_argument("--support-pixel", metavar="K,U,V", action="append",
                   help="the object is held still at pixel column U, row V of frame K (repeat for several "
                        "supports): keeps the still region detected there, or holds the particles within 3 cm of "
                        "that point; detected supports elsewhere are dropped")
    s.add_argument("--support-particles", metavar="I,J,...", help="these particles are held still (the one "
                   "support; replaces the detected ones)")
    s.add_argument("--grasp-radius", type=float, metavar="R", help="the hand holds the particles within R metres "
                   "of the contact (a fingertip's radius for a poke); the video shows where the hand grasps, not "
                   "how much it holds (default: a 3 cm pinch, more when the contact region is larger)")
    s.add_argument("--grasp-frame", metavar="K", help="the hand takes hold of (or starts touching) the object at "
                   "frame K (wins over the detected grasp; recorded on the stage: the contact's source is 'user')")
    s.add_argument("--release-frame", metavar="K", help="the hand lets go at frame K, or 'never' (held to the "
                   "end); wins over the detected release")
    s.add_argument("--no-preview", action="store_true", help="skip the preview PNG")
    s.add_argument("--device", default="cpu", help="cpu or cuda (rendering the object's depth; default cpu)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    return s


def run(a) -> int:
    from .. import api

    log = progress_log(a.json)
    hint = api.parse_hint(a.hint_pixel, a.hint_particles, a.support_pixel, a.support_particles, a.grasp_radius,
                          grasp_frame=a.grasp_frame, release_frame=a.release_frame)
    r = api.extract(a.stage, hint=hint, interaction_type=a.type, preview=not a.no_preview, log=log, device=a.device)
    if a.json:
        print(json.dumps(r.summary(), indent=2, default=str))
    return 0
