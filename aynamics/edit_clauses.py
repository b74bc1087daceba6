"""Where one clause of an edit instruction ends and the next starts, and the patterns of the clauses other modules
read whole (a removal, no gravity, a move).

Clauses are joined by ";", "then" or "and": "and" before a clause's first word joins two clauses ("double the mass
of box_0 and halve its friction"), elsewhere it joins objects ("box_0 and sphere_1") or an add clause's positions.
A replace clause of several replacements is one clause per replacement ("replace box_0 with a sphere and
cylinder_0 with a box").

    split_clauses("Stop box_0 and then double the mass of sphere_1.")
    # ['stop box_0', 'double the mass of sphere_1']
"""

from __future__ import annotations

import re

from aynamics.edit_add import ADD_VERBS, PHRASE_START
from aynamics.edit_replace import REPLACE_CLAUSE, REPLACE_VERBS, WITH_KIND
from aynamics.edit_words import VERBS_BY

MOVE_VERBS = r"(?:move|shift|push|translate)"
REMOVE_CLAUSE = r"(?:remove|delete|take away|take out) (?P<t>.+?)(?: from the scene)?"  # a removal clause
# "turn off gravity", "no gravity", "zero gravity", "make it weightless" (read before a removal: "remove gravity")
NO_GRAVITY = (
    r"(?:(?:turn|switch|shut) off|remove|disable|take away) (?:the )?gravity|(?:use |set |with )?(?:zero|no) gravity"
    r"|(?:set (?:the )?gravity to (?:zero|0|nothing))|(?:make (?:it|everything|the scene|the objects) )?weightless"
)


# the words a clause starts with: "and" before one of them joins two clauses ("double the mass of box_0 and halve its
# friction"); elsewhere it joins objects ("box_0 and sphere_1")
_CLAUSE_START = (
    rf"(?:{VERBS_BY}|set|change|double|triple|quadruple|halve|multiply|scale|reverse|negate|flip|stop|freeze|make|"
    rf"use|switch to|apply|remove|delete|take away|take out|switch off|shut off|disable|zero gravity|no gravity|tilt|"
    rf"pan|{ADD_VERBS}|{REPLACE_VERBS}|{MOVE_VERBS})\b"
)


def split_clauses(instruction: str, names: tuple[str, ...] = ()) -> list[str]:
    """The clauses of an instruction, lower-cased; "and" before an object's name joins objects even where the name is
    a clause verb ("stop box_0 and scale" for an object named scale was refused as the clause "scale")."""
    text = " ".join(instruction.strip().split()).rstrip(".!").lower()
    text = text.replace("per cent", "percent")
    not_name = rf"(?!(?:{'|'.join(re.escape(n.lower()) for n in names)})\b)" if names else ""
    clauses = [c.strip(" ,") for c in re.split(rf";|,? then |,? and then |,? and {not_name}(?={_CLAUSE_START})", text)]
    clauses = [re.sub(r"^(?:please|now) ", "", c) for c in clauses if c.strip(" ,")]
    return [part for c in clauses for part in _replacements(c)]


# "... and cylinder_0 with a box": another target and its kind, after a replace clause's first
# (not before a phrase of the first: "of radius 0.2 and of mass 2 kg and cylinder_0 with a box")
_WITH_KIND = " " + re.sub(r"\(\?P<\w+>", "(?:", WITH_KIND)  # its groups unnamed: re.split returns a pattern's groups
_NEXT_REPLACEMENT = rf",? and (?!{PHRASE_START})(?=.+?{_WITH_KIND})"


def _replacements(clause: str) -> list[str]:
    """A replace clause of several replacements as one clause each, the verb repeated: "replace box_0 with a sphere
    and cylinder_0 with a box" -> "replace box_0 with a sphere", "replace cylinder_0 with a box" (the second was read
    as the first's phrases, and refused). Any other clause as it is."""
    if not (m := re.fullmatch(REPLACE_CLAUSE, clause)):
        return [clause]
    verb = re.match(REPLACE_VERBS, clause).group(0)
    first, *pieces = re.split(_NEXT_REPLACEMENT, m.group("rest"))
    more: list[str] = []
    pending = ""  # a target without its kind joins the next piece ("... and box_1 and cylinder_0 with boxes")
    for piece in pieces:
        piece = f"{pending} and {piece}" if pending else piece
        if re.search(_WITH_KIND, piece):
            more.append(piece)
            pending = ""
        else:
            pending = piece
    return [clause[: m.start("rest")] + first, *(f"{verb} {part}" for part in more)]
