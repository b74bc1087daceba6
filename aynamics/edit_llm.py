"""The optional language-model editor behind `aynamics edit --llm MODEL`.

Any chat model that transformers loads (`AutoTokenizer` + `AutoModelForCausalLM`, a local directory or a hub
name when a hub is reachable) gets the scene's YAML and the instruction, and answers with the edited YAML. The
answer is trusted for nothing:

1. it must parse and validate as a scene (`aynamics.scene.parse`, which also strips fences and prose);
2. it must keep the objects (names, shapes, order) and change something; it may remove the objects the instruction
   removes or replaces and add as many objects of a kind as its 'add' and 'replace' clauses do (`named_additions`);
3. every changed field must be one the instruction names (`named_fields`): "double the mass of
   box_0" lets it change `box_0.physics.mass` and nothing else.

    editor = LLMEditor("Qwen/Qwen2.5-0.5B-Instruct")
    result = editor.edit(scene, "make the sphere twice as heavy")   # EditResult, or EditError when refused
"""

from __future__ import annotations

import re

from aynamics.edit import SHAPE_KEYS, EditResult, check_start
from aynamics.edit_add import ADD_CLAUSE, KINDS, PLURAL, read_count
from aynamics.edit_clauses import REMOVE_CLAUSE, split_clauses
from aynamics.edit_diff import Change, diff
from aynamics.edit_replace import REPLACE_CLAUSE
from aynamics.edit_targets import find_targets
from aynamics.edit_words import DIRECTIONS, QUANTITIES, EditError
from aynamics.scene import Scene, SceneError, dump, parse, require_scene

SYSTEM_PROMPT = (
    "You edit physics scenes written in YAML. Each object has a state (position in m, orientation as a wxyz "
    "quaternion, linear_velocity in m/s and angular_velocity in rad/s, world frame, z up) and physics (friction "
    "[sliding, rolling], mass in kg, damping as log10 of a decay rate in 1/s, optional restitution). Directions: "
    "left is -x, right +x, forward/away from the camera +y, back/toward the camera -y, up +z. Apply the user's "
    "instruction and change nothing else: keep every object (unless the instruction removes it; an object it adds "
    "goes after the others), name and number the instruction does not mention. "
    "Answer with the complete edited scene as YAML in a ```yaml block and nothing else."
)


def build_messages(scene: Scene, instruction: str) -> list[dict[str, str]]:
    """The chat the model sees: the rules, then the scene and the instruction."""
    user = f"Scene:\n```yaml\n{dump(scene)}```\nInstruction: {instruction}"
    return [{"role": "system", "content": SYSTEM_PROMPT}, {"role": "user", "content": user}]


def check_output(scene: Scene, instruction: str, text: str) -> EditResult:
    """Validate a model's answer against the instruction; refuse anything it does not ask for.

    Raises:
        EditError: the answer is not a valid scene, changes the objects, changes nothing, or changes a field the
            instruction does not name (the message lists those changes and the fields it names).
    """
    try:
        edited = parse(text)
    except SceneError as e:
        raise EditError(f"LLM edit refused: the model's answer is not a valid scene: {e}") from None
    try:
        changes = diff(scene, edited)
    except EditError as e:
        raise EditError(f"LLM edit refused: {e}") from None
    if not changes:
        raise EditError(f"LLM edit refused: the model's answer changes nothing for {instruction!r}")
    allowed = named_fields(instruction, scene)
    # an object's bare name allows its removal, not its fields ("double the mass of cylinder_0 and remove box_0"
    # let the model keep box_0 and move it)
    fields = allowed - set(scene.names)
    bad = [c for c in changes if not c.added and outside([c], allowed if c.removed else fields)]
    may_add = named_additions(instruction, scene, removed={c.path for c in changes if c.removed})
    for kind in sorted({c.after for c in changes if c.added}):
        added = [c for c in changes if c.added and c.after == kind]
        if len(added) > may_add.get(kind, 0):  # "add a sphere" let it add two, or a box
            bad.extend(added[may_add.get(kind, 0) :])
    if bad:
        shown = "; ".join(str(c) for c in bad[:6]) + (f"; ... ({len(bad)} in all)" if len(bad) > 6 else "")
        raise EditError(
            f"LLM edit refused: it changes fields that {instruction!r} does not name: {shown}. "
            f"The instruction names: {sorted(allowed) or 'no field the editor knows'}"
        )
    check_start(scene, edited, "LLM edit refused: the model's answer")
    return EditResult(edited, tuple(changes))


# --------------------------------------------------------------------------------------------
# What an instruction names (the check of a free editor's answer)
# --------------------------------------------------------------------------------------------
# Words a free-form instruction uses for a quantity without naming it (for `named_fields` only: the deterministic
# edit language names quantities)
DESCRIBED: tuple[tuple[str, tuple[str, ...]], ...] = (
    (r"heav(?:y|ier|iest)|light(?:er|est)?|weigh(?:s|t)?|massive", ("physics.mass",)),
    (r"fast(?:er|est)?|slow(?:er|est)?|quick(?:er|ly)?|rapid(?:ly)?", ("state.linear_velocity",)),
    (r"spin(?:s|ning)?|rotat(?:e|es|ing|ion)|roll(?:s|ing)?", ("state.angular_velocity",)),
    (r"bounc(?:e|es|y|ier|iest|ing)|elastic", ("physics.restitution",)),
    (r"slipp(?:ery|erier)|grip(?:py|pier)?|sticky|stickier|rough(?:er)?|smooth(?:er)?", ("physics.friction",)),
    (
        r"big(?:ger)?|large(?:r)?|small(?:er)?|tiny|tall(?:er)?|short(?:er)?|wide(?:r)?|grow|shrink",
        ("size", "radius", "height", "state.position"),  # a resting object's centre moves with its shape
    ),
)


# Words for the camera's fields once the camera is named ("rotate the camera", "move the camera back"); "zoom" names
# the field of view wherever it stands
CAMERA_WORDS: tuple[tuple[str, str], ...] = (
    (
        r"mov(?:e|es|ing)|shift|push|pull|translat\w*|rais(?:e|es|ing)|lower|higher|closer|further|farther|"
        r"position|location|place|put|height|elevation",
        "camera.position",
    ),
    (r"rotat\w*|tilt\w*|pitch\w*|turn\w*|angle\w*|orientation|look\w*|point\w*|aim\w*", "camera.orientation"),
)


def named_fields(instruction: str, scene: Scene) -> set[str]:
    """Path prefixes of the fields an instruction names (the edit language's words and those above), for checking
    a free editor.

    Objects named in the text (or 'the box', 'all spheres') restrict the per-object fields; none named means
    every object, unless the camera is named ("rotate the camera": its fields, no object's; "toward the camera" is a
    direction, not the camera). A component named ('x-velocity') restricts a vector to that element. Moves name
    positions, 'stop' names both velocities; a removal clause ('remove box_0') names the object by its bare name,
    which allows its removal and none of its fields (`aynamics.edit_llm.check_output`). An added object has no
    fields here: the 'add' clauses, the clauses after them that say 'it'/'its'/'them'/'their' (and no object of the
    scene) and the added objects' names ('sphere_0', 'named NAME', 'the sphere' where the scene has none) name no
    object of the scene, so not every object either.
    """
    require_scene(scene, "named_fields: scene")
    if not isinstance(instruction, str):  # None / bytes failed on "'NoneType' object has no attribute 'lower'"
        raise TypeError(f"named_fields: instruction is a {type(instruction).__name__}, not a str")
    text = " ".join(instruction.lower().split())
    clauses = split_clauses(instruction, scene.names)
    lower = {n.lower(): n for n in scene.names}

    def names_object_in(low: str, s: str) -> bool:
        return re.search(rf"(?<![\w]){re.escape(low)}(?![\w])", s) is not None

    # "add a sphere at [1, 2] and double its mass" named every object's mass (the clause names no object), and a free
    # editor that doubled box_0's passed; so did one that removed box_0 for "... and remove it"
    new_names, new_kinds, kept, after_add, replaced = set(), set(), [], False, []
    for clause in clauses:
        if (m := re.fullmatch(ADD_CLAUSE, clause)) or (m := re.fullmatch(REPLACE_CLAUSE, clause)):
            if "t" in m.groupdict():  # a replacement: its targets are removed (below), its new objects added
                replaced.append((m.group("t"), KINDS[m.group("k")]))
            after_add = True
            new_kinds.add(KINDS[m.group("k")])
            new_names.update(re.findall(r"\b(?:named|called) ([a-z_][\w.-]*)", m.group("rest")))
        elif not (
            after_add
            and re.search(r"\b(?:it|its|them|their)\b", clause)
            and not any(names_object_in(low, clause) for low in lower)
        ):
            after_add = False
            kept.append(clause)
    new_ref = False  # the text names an added object ("double the mass of sphere_0", "... of the sphere")
    if new_kinds:  # an added object is no field ("add a sphere like box_0 of mass 2 kg" named box_0's mass);
        text, clauses = "; ".join(kept), kept  # `named_additions` counts it
        new_names.update(re.findall(r"\b(?:box|sphere|cylinder)_\d+\b", text))
        new_ref = any(n not in lower and names_object_in(n, text) for n in new_names)
        new_ref |= any(re.search(rf"\b{k}(?:e?s)?\b", text) and k not in scene.structure for k in new_kinds)
    objs = [n for low, n in lower.items() if names_object_in(low, text)]
    for kind in ("box", "sphere", "cylinder"):
        if re.search(rf"\b{kind}(?:e?s)?\b", text):
            objs.extend(o.name for o in scene.objects if o.type == kind)
    # "rotate the camera" named every object's spin and "move the camera back" every position (a free editor that
    # spun the box passed the check, one that turned the camera was refused)
    camera = re.search(r"\bcamera\b", re.sub(r"\b(?:towards?|away from) the camera\b", " ", text)) is not None
    every = re.search(r"\b(?:all|every|each|everything|objects)\b", text) is not None
    objs = sorted(set(objs)) or ([] if (camera or new_ref) and not every else list(scene.names))
    fields: set[str] = set()
    if re.search(r"\bzoom\w*", text):
        fields.add("camera.fovy")
    # "make everything weightless": the gravity, not the masses; "make box_0 weightless" (one object cannot be) names
    # none, as the edit language refuses it
    one = "|".join([r"\b(?:box(?:es)?|spheres?|cylinders?)\b", *(rf"(?<!\w){re.escape(low)}(?!\w)" for low in lower)])
    for before, c in zip(["", *clauses], clauses, strict=False):  # 'it' names an object after a clause that did
        pronoun = r"|\b(?:it|them)\b" if re.search(one, before) else ""  # ("moon gravity then make it weightless")
        if re.search(r"\bweightless\w*", c) and not re.search(one + pronoun, c):
            fields.add("gravity.gravity")
    # "set the fov to 60 and move it 1 m back": 'it' after a clause that edited the camera is the camera
    camera_words = "|".join(q.words for q in QUANTITIES if q.scope == "camera") + r"|camera|zoom\w*"
    spoken = [
        c
        for before, c in zip(clauses, clauses[1:], strict=False)
        if re.search(r"\b(?:it|its|them|their)\b", c) and re.search(rf"\b(?:{camera_words})\b", before)
    ]
    for said in ([text] if camera else []) + spoken:
        fields.update(path for words, path in CAMERA_WORDS if re.search(rf"\b(?:{words})\b", said))
        if any(re.search(rf"\b{re.escape(d)}\b", said) for d in DIRECTIONS):
            fields.add("camera.position")
    for q in QUANTITIES:
        for m in re.finditer(rf"(?:\b(?P<c>[xyz])[- ]?)?\b(?:{q.words})\b", text):
            text_q = m.group(0)
            comp = m.group("c")
            suffix = f"[{q.index}]" if q.index is not None else (f"[{'xyz'.index(comp)}]" if comp else "")
            field = ".".join(q.path) + suffix
            fields.update(f"{h}.{field}" for h in (objs if q.scope == "object" else [q.scope]))
            if q.key in SHAPE_KEYS:  # a resting object's centre moves with its shape (`aynamics.edit`)
                fields.update(f"{o}.state.position" for o in objs)
            text = text.replace(text_q, " ")  # "angular velocity" must not also count as "velocity"
    for words, paths in DESCRIBED:
        if re.search(rf"\b(?:{words})\b", text):
            fields.update(f"{o}.{path}" for o in objs for path in paths)
    if re.search(r"\b(?:move|shift|push|translate|put|place)\b", text) or any(f" {d}" in text for d in DIRECTIONS):
        fields.update(f"{o}.state.position" for o in objs)
    if re.search(r"\b(?:stop|freeze)\b", text):
        fields.update(f"{o}.state.{k}" for o in objs for k in ("linear_velocity", "angular_velocity"))
    # a removal names each object of a removal clause by its bare name: its removal, none of its fields
    # (`check_output` keeps the two apart). "remove" anywhere named every field of every object the text named:
    # "double the mass of cylinder_0 and remove box_0" let a free editor move cylinder_0, "remove the spin of box_0"
    # delete box_0
    removed = [(m.group("t"), None) for clause in clauses if (m := re.fullmatch(REMOVE_CLAUSE, clause))]
    for target, kind in removed + replaced:  # a replacement removes its targets too ("replace box_0 with a sphere")
        if re.fullmatch(r"it|them", target) and target not in lower:
            fields.update(objs)  # "stop box_0 and remove it": the objects the text names
            continue
        try:
            idx = find_targets(target, scene)
        except EditError:  # "remove the spin of box_0" removes no object
            continue
        fields.update(scene.names[i] for i in idx)
        # a replacement by its own kind keeps the name ("replace box_0 with a box of size [...]" is box_0's size
        # changing, `aynamics.edit_replace`): every field of the object, as the new object's
        fields.update(f"{scene.names[i]}.{f}" for i in idx if scene.objects[i].type == kind for f in _OBJECT_FIELDS)
    return fields


_OBJECT_FIELDS = ("size", "radius", "height", "physics", "state")  # an object's fields but its name and type


def named_additions(instruction: str, scene: Scene | None = None, removed: set[str] | None = None) -> dict[str, int]:
    """How many objects of each kind the instruction's 'add' and 'replace' clauses add ('add a sphere at [1, 0]' ->
    {'sphere': 1}, 'replace box_0 with a ball' -> {'sphere': 1}), for checking a free editor: it may add those and
    no more. A replacement of several targets by a plural kind ('replace the boxes with spheres') adds one for each
    of the `scene`'s objects the targets name (without a scene: none, so such an answer is refused). With `removed`
    (the names an answer removed) a replacement counts only where its targets are among them: an answer that keeps
    them ("replace box_0 with a box": box_0 kept and box_1 added) may not add its objects."""
    if not isinstance(instruction, str):
        raise TypeError(f"named_additions: instruction is a {type(instruction).__name__}, not a str")
    if scene is not None:
        require_scene(scene, "named_additions: scene")
    out: dict[str, int] = {}
    for kind, n, replaced in additions(instruction, scene):
        if removed is None or replaced is None or set(replaced) <= removed:
            out[kind] = out.get(kind, 0) + n
    return out


def additions(instruction: str, scene: Scene | None = None) -> list[tuple[str, int, tuple[str, ...] | None]]:
    """Per 'add' or 'replace' clause: (kind, how many it adds, the names of the `scene`'s objects it replaces, or
    None for an add clause or targets that cannot be named without a scene); `named_additions` sums them."""
    out = []
    for clause in split_clauses(instruction, scene.names if scene is not None else ()):
        replaced = None
        if m := re.fullmatch(ADD_CLAUSE, clause):
            n = read_count(m.group("n"), clause)  # "add two spheres at ..." adds 2
        elif m := re.fullmatch(REPLACE_CLAUSE, clause):
            try:
                targets = find_targets(m.group("t"), scene) if scene is not None else None
            except EditError:  # names no object of the scene: the deterministic editor refuses it too
                targets = []
            replaced = None if targets is None else tuple(scene.names[i] for i in targets)
            if m.group("n"):
                n = read_count(m.group("n"), clause)
            elif m.group("k") not in PLURAL:
                n = 1
            else:
                n = len(targets) if targets is not None else 0
        else:
            continue
        out.append((KINDS[m.group("k")], n, replaced))
    return out


_PATHS = "set of str field paths (named_fields gives one)"


def outside(changes: list[Change] | tuple[Change, ...], allowed: set[str]) -> list[Change]:
    """The changes whose path does not start with one of the allowed prefixes.

    Raises:
        TypeError: `changes` is not a list of `Change`s, or `allowed` not a collection of str path prefixes (a str
            was read as its letters: every change was outside "box_0.mass", and "b.x" inside "box_0").
    """
    for name, value, want in (("changes", changes, "list of Changes (diff gives one)"), ("allowed", allowed, _PATHS)):
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
            raise TypeError(f"outside: {name} is a {type(value).__name__} {value!r:.60}: must be a {want}")
    changes, allowed = list(changes), tuple(allowed)  # a generator of paths was spent on the first change
    for k, c in enumerate(changes):
        if not isinstance(c, Change):
            raise TypeError(f"outside: changes[{k}] is a {type(c).__name__} {c!r:.60}: must be a Change")
    for a in allowed:
        if not isinstance(a, str):
            raise TypeError(f"outside: allowed holds a {type(a).__name__} {a!r:.60}: must be a {_PATHS}")
    return [c for c in changes if not any(c.path == a or c.path.startswith((a + ".", a + "[")) for a in allowed)]


class LLMEditor:
    """A transformers chat model that edits scenes; outputs pass `check_output` before they are returned."""

    def __init__(self, model: str, *, max_new_tokens: int = 2048, device: str = "auto") -> None:
        """Load the tokenizer and model.

        Args:
            model: a local checkpoint directory or a hub name (`from_pretrained`).
            max_new_tokens: generation limit; a scene of a few objects is ~300–600 tokens.
            device: torch device to run on ("auto": a GPU when there is one, else the CPU).

        Raises:
            EditError: max_new_tokens < 1, the model or tokenizer can't be loaded, or the tokenizer has no chat
                template.
        """
        from transformers import AutoModelForCausalLM, AutoTokenizer

        from aynamics.lm import inference_device

        if max_new_tokens < 1:  # before loading: generate() refuses it only after
            raise EditError(f"--max-new-tokens {max_new_tokens}: must be >= 1")
        try:
            device = str(inference_device(device))
        except ValueError as e:
            raise EditError(f"--llm {model!r}: {e}") from None
        try:
            self.tokenizer = AutoTokenizer.from_pretrained(model)
            self.model = AutoModelForCausalLM.from_pretrained(model).to(device).eval()
        except (OSError, ValueError) as e:
            # on one line, whole up to 400 characters: its first line alone ended at "... from one of:" (helper-93)
            said = " ".join(str(e).split())
            said = (said[:397] + "...") if len(said) > 400 else said or type(e).__name__
            raise EditError(f"--llm {model!r}: cannot load a chat model with transformers: {said}") from None
        if not getattr(self.tokenizer, "chat_template", None):
            raise EditError(f"--llm {model!r}: the tokenizer has no chat template; give an instruction-tuned model")
        self.name = model
        self.max_new_tokens = max_new_tokens
        self.device = device

    def generate(self, scene: Scene, instruction: str) -> str:
        """The model's raw answer (greedy decoding) to the edit chat."""
        import torch

        inputs = self.tokenizer.apply_chat_template(
            build_messages(scene, instruction), add_generation_prompt=True, return_tensors="pt", return_dict=True
        ).to(self.device)
        pad = self.tokenizer.pad_token_id if self.tokenizer.pad_token_id is not None else self.tokenizer.eos_token_id
        with torch.no_grad():
            out = self.model.generate(**inputs, max_new_tokens=self.max_new_tokens, do_sample=False, pad_token_id=pad)
        return self.tokenizer.decode(out[0, inputs["input_ids"].shape[1] :], skip_special_tokens=True)

    def edit(self, scene: Scene, instruction: str) -> EditResult:
        """Ask the model for the edit and validate its answer (see `check_output`)."""
        return check_output(scene, instruction, self.generate(scene, instruction))
