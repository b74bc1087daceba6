"""Which objects a clause of the edit language (`aynamics.edit`) names: target phrases ("box_0 and sphere_1",
"all boxes", "the sphere"), 'it' / 'them' for the objects of the clause before, and the objects an earlier clause
removed.

    find_targets("the cylinder and box_0", scene)   # [0, 1]: indices into scene.names (box_0, cylinder_0)
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from aynamics.edit_words import UNDERSTOOD, EditError, is_quantity
from aynamics.scene import OBJECT_TYPES, Scene


@dataclass(frozen=True)
class ObjectView:
    """The objects of the edited items as the clauses so far left them (a `Scene` reads the same): their names and
    types, the objects an earlier clause added included."""

    names: tuple[str, ...]
    structure: tuple[str, ...]


def object_view(items: list[dict]) -> ObjectView:
    """The objects of the edited items, those removed so far included (objects come first among the items, so an
    object's index is its item's)."""
    objects = [it for it in items if it["type"] in OBJECT_TYPES]
    return ObjectView(tuple(it["name"] for it in objects), tuple(it["type"] for it in objects))


def find_targets(
    text: str | None,
    scene: Scene | ObjectView,
    previous: list[int] | str | None = None,
    gone: frozenset[int] = frozenset(),
) -> list[int]:
    """Indices of the objects a target phrase names; None or 'all objects' means every object; 'it' / 'them' the
    objects of the clause before (`previous`), unless an object has that name ("stop it" stops an object named it).
    Every object and the objects of a kind ('all boxes', 'the box') leave out those an earlier clause removed
    (`gone`): "remove box_0 and double the mass of all objects" was refused as editing box_0."""
    lower = {n.lower(): i for i, n in enumerate(scene.names)}
    if text is not None and re.fullmatch(r"it|them", text) and text not in lower:
        return previous_targets(text, previous, scene)
    if text is None or re.fullmatch(r"(?:all|every|each)(?: (?:the )?objects?)?|everything|the objects", text):
        return [i for i in range(len(scene.names)) if i not in gone]
    left = [n for i, n in enumerate(scene.names) if i not in gone]  # a same-kind replacement's name once, not twice
    out: list[int] = []
    for part in re.split(r"\s*,\s*(?:and\s+)?|\s+and\s+", text.strip()):
        part = part.strip()
        bare = re.sub(r"^the ", "", part)  # "the crate" for an object named crate
        if part in lower or bare in lower:
            out.append(lower[part if part in lower else bare])
            continue
        m = re.fullmatch(r"(?:(all|every|each|the) )?(box|boxes|sphere|spheres|cylinder|cylinders)", part)
        if m is None:
            if is_quantity(part):  # "double the mass of box_0 and the friction": a second quantity, not an object
                raise EditError(
                    f"{part!r} is a quantity, not an object of the scene {left}: one clause changes one "
                    f"quantity; repeat a verb before {part!r} (e.g. 'double the mass of {scene.names[0]} and halve "
                    "its friction')"
                )
            raise EditError(f"object {part!r} not found; the scene has {left}. {UNDERSTOOD}")
        kind = {"boxes": "box", "spheres": "sphere", "cylinders": "cylinder"}.get(m.group(2), m.group(2))
        idx = [i for i, t in enumerate(scene.structure) if t == kind and i not in gone]
        if not idx:
            raise EditError(f"{part!r}: the scene has no {kind}{' left' if gone else ''}; its objects are {left}")
        singular = m.group(2) == kind and m.group(1) in (None, "the")
        if singular and len(idx) > 1:
            names = [scene.names[i] for i in idx]
            plural = "boxes" if kind == "box" else f"{kind}s"  # it said "2 spherees"
            raise EditError(f"{part!r} is ambiguous: the scene has {len(idx)} {plural} {names}; name one")
        out.extend(idx)
    return sorted(set(out))


def previous_targets(word: str, previous: list[int] | str | None, scene: Scene | ObjectView) -> list[int]:
    """The objects an earlier clause named, for 'it', 'its', 'them', 'their' (alone they meant every object:
    "double the mass of box_0; halve its friction" halved every object's friction); in a scene of one object,
    before any clause named one, that object. After a clause that edited the camera (`previous` is its text) the
    word means the camera, which `aynamics.edit` reads where the camera has the field ("... and move it 1 m back");
    here, where an object's field is asked for ("set the fov to 60 and stop it"), it is refused."""
    if isinstance(previous, str):
        raise EditError(
            f"{word!r} follows {previous!r}, which edited the camera, so it could mean the camera; name the object "
            f"(e.g. {scene.names[0]})"
        )
    if previous is None and len(scene.names) == 1:
        return [0]
    if previous is None:
        raise EditError(
            f"{word!r} refers to no object named before it in the instruction; name the object (e.g. {scene.names[0]})"
        )
    return previous


REMOVED = "__removed__"  # marks an object item a clause removed; `apply_instruction` drops it at the end


def gone(items: list[dict]) -> frozenset[int]:
    """Indices of the items an earlier clause removed (marked `REMOVED`)."""
    return frozenset(i for i, item in enumerate(items) if item.get(REMOVED))


def check_not_removed(items: list[dict], idx: list[int], clause: str) -> None:
    """Raise EditError naming the clause when it edits an object an earlier clause removed."""
    for i in idx:
        if items[i].get(REMOVED):
            raise EditError(f"{clause!r}: {items[i]['name']} was removed by an earlier clause")
