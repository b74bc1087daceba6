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
