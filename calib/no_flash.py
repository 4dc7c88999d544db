"""Which photos were taken with the flash off (issue 39, flash/no-flash pairs).

A no-flash photo from about a flash photo's viewpoint sees the room's light alone, so the fit observes the
per-texel ambient radiance directly instead of telling it from the albedo by the few per cent the flash's
falloff and angle vary between views. Such a photo is a frame marked ``no_flash`` (capture_json.py), whose flash
the stages that place it give intensity 0 (:func:`texstream.calib.lights.colocated_light`).

Which photos they are, in order of precedence:

1. ``--no-flash GLOB`` (ingest, run, the camera imports): the photos whose file name (or name without its
   extension) matches the glob, whatever their EXIF says; a glob that matches none is an error (a typo would
   otherwise fit every photo as lit);
2. the EXIF ``Flash`` tag (0x9209, bit 0: fired; OpenImageIO's ``Exif:Flash``): photos whose tag says the flash
   did not fire, but only when another photo's says it fired. A capture in which no photo fired a flash was lit
   by something else (a lamp, a ring light the camera does not know about): its tags say nothing about that
   light, so none is marked;
3. else none.
"""

from __future__ import annotations

import fnmatch
from pathlib import Path

from texstream.core.errors import ConfigError

NO_FLASH_HELP = ("photos taken with the flash off (a flash/no-flash pair's second photo: the room's light alone), "
                 "a file-name glob such as '*_noflash.*'; overrides the EXIF Flash tag, which otherwise marks "
                 "the photos whose flash did not fire when others' did")


def exif_flash_fired(value) -> bool | None:
    """Whether an EXIF ``Flash`` value says the flash fired (bit 0), None when the tag is absent or says the
    camera has no flash (bit 5: such a camera's photos say nothing about a pair)."""
    if value is None or int(value) & 0x20:
        return None
    return bool(int(value) & 1)


def read_flash_fired(path: str | Path) -> bool | None:
    """The EXIF ``Flash`` tag of a photo file (:func:`exif_flash_fired`), None when absent or unreadable."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return None
    try:
        return exif_flash_fired(inp.spec().getattribute("Exif:Flash"))
    finally:
        inp.close()


def glob_matches(name: str, pattern: str) -> bool:
    """Whether a photo's file name, or its name without the extension, matches ``pattern``."""
    return fnmatch.fnmatchcase(name, pattern) or fnmatch.fnmatchcase(Path(name).stem, pattern)


def decide_no_flash(fired: dict[str, bool | None], pattern: str | None) -> tuple[set[str], dict]:
    """(the no-flash photos' names, the report's entry {"photos", "source", "why"}) for photos ``fired`` ({file
    name: EXIF says fired, None: no tag}) and the ``--no-flash`` glob (module doc).

    Raises:
        ConfigError: the glob matches none of the photos.
    """
    names = sorted(fired)
    if pattern:
        marked = {n for n in names if glob_matches(n, pattern)}
        if not marked:
            raise ConfigError(f"--no-flash {pattern!r} matches none of the {len(names)} photos (e.g. {names[0]})",
                              fix="give a glob of the no-flash photos' file names, e.g. '*_noflash.*'")
        return marked, {"photos": len(marked), "source": "--no-flash",
                        "why": f"--no-flash {pattern!r} matches {len(marked)} of {len(names)} photos"}
    fired_yes = [n for n in names if fired[n] is True]
    fired_no = {n for n in names if fired[n] is False}
    if fired_yes and fired_no:
        return fired_no, {"photos": len(fired_no), "source": "exif",
                          "why": f"the EXIF Flash tag says the flash did not fire in {len(fired_no)} of {len(names)} "
                                 f"photos (and fired in {len(fired_yes)})"}
    if fired_no:
        why = "the EXIF Flash tag says no photo fired a flash: none is taken as a no-flash photo of a pair"
    else:
        why = "no EXIF Flash tag says a flash did not fire, and no --no-flash glob"
    return set(), {"photos": 0, "source": "none", "why": why}
