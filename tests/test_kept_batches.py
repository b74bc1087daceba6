"""`kept_batches`: the content digest that tells a kept batch's records from others under the same keys, and the
folder's settings and lock (exercised end to end by the preference and evaluation tests)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from PIL import Image

from aynamics.kept_batches import KeptBatches, content_digest, file_digest, partial_folder


@dataclasses.dataclass
class _Held:
    a: np.ndarray
    b: str | None = None


def test_content_digest_follows_contents_not_identity():
    """Equal contents give one digest, whatever object holds them; a changed value, dtype, shape, key or order does
    not; a kind it cannot read is named."""
    arr = np.arange(6, dtype=np.int16).reshape(2, 3)
    base = content_digest({"x": torch.tensor([1.0, 2.0]), "y": [arr, "s", None]}, _Held(arr), Image.new("L", (2, 2)))
    same = content_digest(
        {"y": [arr.copy(), "s", None], "x": torch.tensor([1.0, 2.0])}, _Held(arr.copy()), Image.new("L", (2, 2))
    )
    assert base == same and len(base) == 16
    others = [
        content_digest({"x": torch.tensor([1.0, 2.5]), "y": [arr, "s", None]}, _Held(arr), Image.new("L", (2, 2))),
        content_digest(
            {"x": torch.tensor([1.0, 2.0]), "y": [arr.astype(np.int32), "s", None]}, _Held(arr), Image.new("L", (2, 2))
        ),
        content_digest(
            {"x": torch.tensor([1.0, 2.0]), "y": [arr.reshape(3, 2), "s", None]}, _Held(arr), Image.new("L", (2, 2))
        ),
        content_digest({"z": torch.tensor([1.0, 2.0]), "y": [arr, "s", None]}, _Held(arr), Image.new("L", (2, 2))),
        content_digest({"x": torch.tensor([1.0, 2.0]), "y": ["s", arr, None]}, _Held(arr), Image.new("L", (2, 2))),
        content_digest({"x": torch.tensor([1.0, 2.0]), "y": [arr, "s", None]}, _Held(arr, "b"), Image.new("L", (2, 2))),
        content_digest({"x": torch.tensor([1.0, 2.0]), "y": [arr, "s", None]}, _Held(arr), Image.new("L", (2, 2), 1)),
    ]
    assert len({base, *others}) == 1 + len(others)
    assert content_digest(torch.tensor([1, 2], dtype=torch.bfloat16)) != content_digest(torch.tensor([1.0, 2.0]))
    assert content_digest(1) != content_digest(1.0) != content_digest("1")
    with pytest.raises(TypeError, match="a set cannot be hashed"):
        content_digest({1, 2})


def test_kept_batches_keep_streams_apart_and_bind_settings_once_a_batch_is_kept(tmp_path):
    """Two streams number their batches apart; settings bind only once a batch is kept (the mismatch named); a gap
    in a stream's numbers is named; a second opener is refused while the first holds the lock; the partial folder
    sits beside OUT; a file's digest follows its bytes."""
    fields = {"a": frozenset({"v"}), "b": frozenset({"v"})}
    kept = KeptBatches(tmp_path / "out.partial", {"n": 1}, run="a test run", verb="score", fields=fields)
    with kept.opened():
        kept.save("a", 0, {"v": 1})
        kept.save("a", 1, {"v": 2})
        kept.save("b", 0, {"v": 3})
        assert [b["v"] for b in kept.done("a")] == [1, 2] and kept.done("b") == [{"v": 3}] and len(kept) == 3
        with pytest.raises(ValueError, match="another process is scoring into"):
            with KeptBatches(kept.folder, {"n": 1}, run="a test run", verb="score", fields=fields).opened():
                pass
    with pytest.raises(ValueError, match=r"with other settings \(n 1 there, 2 now\)"):
        with KeptBatches(kept.folder, {"n": 2}, run="a test run", verb="score", fields=fields).opened():
            pass
    (kept.folder / "b-000000.pt").write_bytes(b"PK\x03\x04 not a batch")  # a disk's garbage: named, no traceback
    with kept.opened(), pytest.raises(ValueError, match=r"b-000000.pt' cannot be read \("):
        kept.done("b")
    (kept.folder / "a-000000.pt").unlink()
    with kept.opened(), pytest.raises(ValueError, match="a-000001.pt': batch 0 is missing before it"):
        kept.done("a")
    kept.remove()
    fresh = KeptBatches(kept.folder, {"n": 2}, run="a test run", verb="score", fields=fields)
    with fresh.opened():  # nothing kept: nothing binds
        assert len(fresh) == 0
    assert partial_folder(tmp_path / "out") == (tmp_path / "out.partial").resolve()
    (tmp_path / "f").write_bytes(b"abc")
    assert file_digest(tmp_path / "f") == "ba7816bf8f01cfea" and file_digest(tmp_path / "none") is None


def test_kept_batches_of_another_command_are_refused_not_taken_over(tmp_path):
    """An interrupted `aynamics preferences --out OUT` kept batch-000000.pt in OUT.partial; `aynamics evaluate --out
    OUT` (streams responses, refined, average-refined) is refused, naming it, and the folder is left as it was, and
    the reverse. Each counted the other's batches as none kept: it wrote its own settings.json over the other's and
    deleted the folder, with the other command's batches, once its OUT was written."""
    from aynamics.evaluate import KEPT_FIELDS
    from aynamics.preference_data import SamplingProgress

    prefs = SamplingProgress(tmp_path / "a.partial", {"seed": 0})
    with prefs.opened():
        prefs.save(prefs.STREAM, 0, {"v": 1})
    before = {p.name: p.read_bytes() for p in prefs.folder.iterdir()}
    evaluation = KeptBatches(prefs.folder, {"num": 3}, run="an evaluation", verb="score", fields=KEPT_FIELDS)
    with pytest.raises(ValueError, match=r"a\.partial' holds 'batch-000000\.pt', which an evaluation does not keep"):
        with evaluation.opened():
            pass
    assert {p.name: p.read_bytes() for p in prefs.folder.iterdir()} == before
    evaluation = KeptBatches(tmp_path / "b.partial", {"num": 3}, run="an evaluation", verb="score", fields=KEPT_FIELDS)
    with evaluation.opened():
        evaluation.save("responses", 0, {"v": 1})
        evaluation.save("average-refined", 0, {"v": 1})
    with pytest.raises(ValueError, match=r"'average-refined-000000\.pt' and 1 more files, which a preference run"):
        with SamplingProgress(evaluation.folder, {"seed": 0}).opened():
            pass
    with evaluation.opened():  # its own batches, and a save a crash cut short, are its own
        (evaluation.folder / "refined-000000.tmp").write_bytes(b"")
        assert len(evaluation) == 2


def test_a_run_killed_writing_its_first_settings_is_gone_on_from(tmp_path):
    """A run killed between writing settings.tmp and renaming it settings.json (before any batch) left the folder
    with .lock and settings.tmp: the same command starts afresh. It was refused as "not the kept batches (no
    settings.json): move it away"."""
    folder = tmp_path / "out.partial"
    folder.mkdir()
    (folder / ".lock").write_text("")
    (folder / "settings.tmp").write_text('{"n": ')
    kept = KeptBatches(folder, {"n": 1}, run="a test run", verb="score", fields={"a": frozenset({"v"})})
    with kept.opened():
        assert len(kept) == 0 and (folder / "settings.json").read_text() == '{\n "n": 1\n}\n'


def test_a_run_that_kept_no_batch_leaves_no_folder(tmp_path):
    """A run refused or failing before its first batch (`aynamics evaluate --num 0 --out OUT`, a data set it cannot
    read) deleted nothing of its own: OUT.partial stayed beside OUT with settings.json and .lock alone. It goes now;
    one that kept a batch (and a stale settings.json an old failure left) stays for the next run to go on from."""
    fields = {"a": frozenset({"v"})}
    kept = KeptBatches(tmp_path / "out.partial", {"n": 1}, run="a test run", verb="score", fields=fields)
    with pytest.raises(ValueError, match="refused"), kept.opened():
        assert (kept.folder / "settings.json").is_file()
        raise ValueError("refused")
    assert not kept.folder.exists()
    with pytest.raises(KeyboardInterrupt), kept.opened():
        kept.save("a", 0, {"v": 1})
        raise KeyboardInterrupt
    assert sorted(p.name for p in kept.folder.iterdir()) == [".lock", "a-000000.pt", "settings.json"]


def test_kept_refinements_of_other_physics_are_done_again(tmp_path, monkeypatch):
    """A refinement kept by `aynamics evaluate --refine 6 --out OUT` under physics 2 is not gone on from once the
    code simulates otherwise (PHYSICS_VERSION raised, as `generate` refuses such a resume): it is forgotten, to be
    done again, naming the setting, and the kept responses (which do not simulate) stay. Without --refine nothing
    kept depends on the physics: it binds nothing. The physics was not among the settings, and the refined scenes of
    two physics were mixed in one table."""
    from aynamics import simulate
    from aynamics.evaluate_cli import evaluation_progress

    (tmp_path / "adapter").mkdir()
    settings = {"adapter": str(tmp_path / "adapter"), "data": "d", "num": 1, "refine": 6}
    kept = evaluation_progress(tmp_path / "out", settings)
    with kept.opened():
        kept.save("responses", 0, {"keys": [0], "digests": ["x"], "texts": ["y"]})
        kept.save("refined", 0, {"keys": [0], "digests": ["x"], "texts": ["y"], "timed_out": 0})
    monkeypatch.setattr(simulate, "PHYSICS_VERSION", simulate.PHYSICS_VERSION + 1)
    with evaluation_progress(tmp_path / "out", settings).opened() as again:
        v = simulate.PHYSICS_VERSION
        assert again.redone == ([f"physics {v - 1} there, {v} now"], ["average-refined", "refined"])
        assert again.count("refined") == 0 and again.count("responses") == 1
    assert evaluation_progress(tmp_path / "out", settings | {"refine": 0}).settings["physics"] is None


def test_settings_only_some_streams_depend_on_redo_those_streams(tmp_path):
    """Stream "b" depends on setting x (a refinement's budget), stream "a" does not: reopened with another x, the
    batches of b are forgotten and a's kept, the new settings recorded; another value of a setting both depend on
    is refused, and nothing is dropped."""
    fields = {"a": frozenset({"v"}), "b": frozenset({"v"})}

    def opened(**settings):
        return KeptBatches(
            tmp_path / "p", settings, run="a test run", verb="score", fields=fields, redone_on={"x": ("b",)}
        )

    kept = opened(n=1, x=1)
    with kept.opened():
        kept.save("a", 0, {"v": 1})
        kept.save("b", 0, {"v": 2})
    again = opened(n=1, x=2)
    with again.opened():
        assert again.redone == (["x 1 there, 2 now"], ["b"])
        assert again.done("a") == [{"v": 1}] and again.count("b") == 0
        again.save("b", 0, {"v": 3})
    with pytest.raises(ValueError, match=r"other settings \(n 1 there, 2 now; x 2 there, 3 now\)"):
        with opened(n=2, x=3).opened():
            pass
    with opened(n=1, x=2).opened() as same:
        assert same.redone is None and same.done("b") == [{"v": 3}]
