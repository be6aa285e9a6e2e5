"""Batched eigensolvers (`certify.arith.linalg`): chunked and with a fallback, as on a GPU, they
give what one call gives."""

from __future__ import annotations

import torch

from certify.arith.linalg import chunked, eigh, eigvalsh

F64 = torch.float64


def _sym(shape: tuple[int, ...], n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(*shape, n, n, generator=g, dtype=F64)
    return A + A.transpose(-1, -2)


def test_chunks_and_refused_chunks_give_the_one_call_values() -> None:
    S = _sym((5, 7), 4, 0)  # 35 matrices, chunks of 8: the last one short
    calls = []

    def refuse_every_second(part: torch.Tensor) -> torch.Tensor:
        calls.append(len(part))
        if len(calls) % 2 == 0:
            raise RuntimeError("cusolver error: CUSOLVER_STATUS_INTERNAL_ERROR")
        return torch.linalg.eigvalsh(part)

    fell_back = []

    def on_the_cpu(part: torch.Tensor) -> torch.Tensor:
        fell_back.append(len(part))
        return torch.linalg.eigvalsh(part)

    got = chunked(refuse_every_second, S, chunk=8, fallback=on_the_cpu)
    assert calls == [8, 8, 8, 8, 3] and fell_back == [8, 8]
    assert got.shape == (5, 7, 4)
    assert torch.allclose(got, torch.linalg.eigvalsh(S), rtol=0, atol=1e-12)


def test_chunked_eigh_keeps_vectors_with_their_values() -> None:
    S = _sym((11,), 3, 1)
    vals, vecs = chunked(lambda A: tuple(torch.linalg.eigh(A)), S, chunk=4)
    assert vals.shape == (11, 3) and vecs.shape == (11, 3, 3)
    assert torch.allclose(S @ vecs, vecs * vals[:, None, :], atol=1e-12)


def test_cpu_calls_are_lapacks_own() -> None:
    S = _sym((6,), 5, 2)
    assert torch.equal(eigvalsh(S), torch.linalg.eigvalsh(S))
    assert torch.equal(eigh(S)[1], torch.linalg.eigh(S).eigenvectors)


def test_default_fallback_solves_a_refused_chunk_on_the_cpu() -> None:
    S = _sym((9,), 3, 3)
    seen = []

    def refuse_first(part: torch.Tensor) -> torch.Tensor:
        seen.append(len(part))
        if len(seen) == 1:
            raise RuntimeError("cusolver error")
        return torch.linalg.eigvalsh(part)

    got = chunked(refuse_first, S, chunk=4)
    assert seen == [4, 4, 4, 1]  # the first chunk again (on the CPU copy), then the rest
    assert torch.allclose(got, torch.linalg.eigvalsh(S), rtol=0, atol=1e-12)
