"""The transformer: shapes, causality, and KV-cached decoding equal to a full forward."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from ttompc.policy import Decoder, ModelConfig, TrajectoryGPT

N, M, L, B = 6, 3, 7, 2


LAYOUTS = pytest.mark.parametrize("layout", ["interleaved", "stacked"])


def _model(dtype: torch.dtype = torch.float32, seed: int = 0, layout: str = "interleaved") -> TrajectoryGPT:
    torch.manual_seed(seed)
    cfg = ModelConfig(
        state_dim=N,
        control_dim=M,
        n_embd=32,
        n_layer=2,
        n_head=4,
        max_steps=10,
        dropout=0.1,
        layout=layout,  # type: ignore[arg-type]
    )
    return TrajectoryGPT(cfg).to(dtype).eval()


def _inputs(dtype: torch.dtype = torch.float32, seed: int = 1) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=dtype)  # noqa: E731
    return {
        "goals": r(B, L, N),
        "rtg": r(B, L, 1),
        "ctg": r(B, L, 1),
        "states": r(B, L, N),
        "actions": r(B, L, M),
        "timesteps": torch.arange(L).expand(B, -1),
    }


@LAYOUTS
def test_shapes_and_paper_size(layout: str) -> None:
    a, s = _model(layout=layout)(**_inputs())
    assert a.shape == (B, L, M) and s.shape == (B, L, N)
    paper = TrajectoryGPT(ModelConfig())
    assert 10.5e6 < paper.num_parameters() < 11.5e6  # the reference prints "GPT size: 11.1M parameters"


def test_rejects_bad_config() -> None:
    with pytest.raises(ValueError, match="divisible"):
        ModelConfig(n_embd=30, n_head=4)
    with pytest.raises(ValueError, match="layout"):
        ModelConfig(layout="braided")  # type: ignore[arg-type]


@LAYOUTS
@pytest.mark.parametrize("field", ["goals", "rtg", "ctg", "states", "actions"])
def test_causality(field: str, layout: str) -> None:
    """Changing step j's inputs never changes predictions of earlier steps, nor a_j when the input is a_j."""
    model, x = _model(layout=layout), _inputs()
    a0, s0 = model(**x)
    j = 4
    y = dict(x)
    y[field] = x[field].clone()
    y[field][:, j] += 10.0
    a1, s1 = model(**y)
    torch.testing.assert_close(a1[:, :j], a0[:, :j], rtol=0, atol=1e-6)
    torch.testing.assert_close(s1[:, :j], s0[:, :j], rtol=0, atol=1e-6)
    if field == "actions":  # a_j enters after the state token of its own step (stacked: with step j+1's token)
        torch.testing.assert_close(a1[:, j], a0[:, j], rtol=0, atol=1e-6)
        assert (s1[:, j] - s0[:, j]).abs().max() > 1e-5
    else:
        assert (a1[:, j] - a0[:, j]).abs().max() > 1e-5


@LAYOUTS
@pytest.mark.parametrize(("dtype", "atol"), [(torch.float32, 1e-5), (torch.float64, 1e-10)])
def test_kv_cache_matches_full_forward(dtype: torch.dtype, atol: float, layout: str) -> None:
    """Feeding the tokens in uneven chunks through the cache, by ``encode`` or by a ``Decoder`` (of a model left in
    train mode: it never drops out), gives the full forward's hidden states."""
    model, x = _model(dtype, layout=layout), _inputs(dtype)
    x["prev_actions"] = x.pop("actions")[:, :-1]
    tokens = model.embed_steps(**x)  # (B, 5L-1, d) interleaved, (B, L, d) stacked
    full = model.encode(tokens)
    sizes = (4, 1, 5, 2, 3, 1, 9, 9) if layout == "interleaved" else (1, 2, 1, 3)
    assert sum(sizes) == tokens.shape[1] == L * model.cfg.tokens_per_step - (layout == "interleaved")
    for decoded in ("encode", "decoder"):
        cache = model.new_cache(B)
        decode = Decoder(model.train(), cache) if decoded == "decoder" else partial(model.eval().encode, cache=cache)
        chunks, i = [], 0
        for size in sizes:
            chunks.append(decode(tokens[:, i : i + size]))
            i += size
        assert cache.length == i
        torch.testing.assert_close(torch.cat(chunks, dim=1), full, rtol=0, atol=atol, msg=decoded)
    # Truncated back, the cache continues as if the dropped tokens had never been fed.
    cache.truncate(i - 3)
    torch.testing.assert_close(decode(tokens[:, i - 3 :]), full[:, i - 3 :], rtol=0, atol=atol)
    with pytest.raises(ValueError, match="truncate"):
        cache.truncate(i + 1)


@LAYOUTS
@pytest.mark.parametrize("start", [0, 3])
def test_step_embedding_is_embed_steps_of_a_window(layout: str, start: int) -> None:
    """base + z @ W reproduces ``embed_steps`` of a window that holds goal and ctg, step by step (a zero a_{-1} at
    step 0, whose interleaved first token is dropped)."""
    model, x = _model(torch.float64, layout=layout), _inputs(torch.float64)
    H, T = 4, model.cfg.tokens_per_step
    goal, ctg = x["goals"][:, 0], x["ctg"][:, 0]
    base, W = model.step_embedding(goal, ctg, start, H)
    assert base.shape == (B, H, T * model.cfg.n_embd) and W.shape == (1 + N + M, T * model.cfg.n_embd)
    for j in range(H):
        k = start + j
        prev = x["actions"][:, j : j + 1] if k > 0 else torch.zeros(B, 1, M, dtype=torch.float64)
        z = torch.cat([x["rtg"][:, j], x["states"][:, j], prev[:, 0]], dim=1)  # (B, 1+n+m)
        tok = (base[:, j] + z @ W).view(B, T, -1)
        steps = torch.full((B, 1), k)
        ref = model.embed_steps(
            goal[:, None], x["rtg"][:, j : j + 1], ctg[:, None], x["states"][:, j : j + 1], prev[:, k == 0 :], steps
        )
        torch.testing.assert_close(tok[:, 1:] if k == 0 and layout == "interleaved" else tok, ref, rtol=0, atol=1e-12)


def test_cache_overflow_is_an_error() -> None:
    model = _model()
    too_long = torch.zeros(1, model.cfg.max_tokens + 1, model.cfg.n_embd)
    with pytest.raises(ValueError, match="overflow"):
        model.encode(too_long, model.new_cache(1))
    with pytest.raises(ValueError, match="overflow"):
        Decoder(model, model.new_cache(1))(too_long)
