"""The optional language-model editor behind `aynamics edit --llm MODEL`.

Any chat model that transformers loads (`AutoTokenizer` + `AutoModelForCausalLM`, a local directory or a hub
name when a hub is reachable) gets the scene's YAML and the instruction, and answers with the edited YAML. The
answer is trusted for nothing:

1. it must parse and validate as a scene (`aynamics.scene.parse`, which also strips fences and prose);
2. it must keep the objects (count, names, shapes) and change at least one number;
3. every changed field must be one the instruction names (`aynamics.edit.named_fields`): "double the mass of
   box_0" lets it change `box_0.physics.mass` and nothing else.

    editor = LLMEditor("Qwen/Qwen2.5-0.5B-Instruct")
    result = editor.edit(scene, "make the sphere twice as heavy")   # EditResult, or EditError when refused
"""

from __future__ import annotations

from aynamics.edit import EditError, EditResult, diff, named_fields, outside
from aynamics.scene import Scene, SceneError, dump, parse

SYSTEM_PROMPT = (
    "You edit physics scenes written in YAML. Each object has a state (position in m, orientation as a wxyz "
    "quaternion, linear_velocity in m/s and angular_velocity in rad/s, world frame, z up) and physics (friction "
    "[sliding, rolling], mass in kg, damping as log10 of a decay rate in 1/s, optional restitution). Directions: "
    "left is -x, right +x, forward/away from the camera +y, back/toward the camera -y, up +z. Apply the user's "
    "instruction and change nothing else: keep every object (unless the instruction removes it), name and number "
    "the instruction does not mention. "
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
    bad = [c for c in changes if outside([c], allowed if c.removed else fields)]
    if bad:
        shown = "; ".join(str(c) for c in bad[:6]) + (f"; ... ({len(bad)} in all)" if len(bad) > 6 else "")
        raise EditError(
            f"LLM edit refused: it changes fields that {instruction!r} does not name: {shown}. "
            f"The instruction names: {sorted(allowed) or 'no field the editor knows'}"
        )
    return EditResult(edited, tuple(changes))


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
