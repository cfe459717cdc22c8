import logging

import numpy as np
import pytest
import sentencepiece

from pi0_jax.tokenizer import PaligemmaTokenizer, discretize_state, state_prompt


@pytest.fixture(scope="module")
def sp(sp_model_path):
    return sentencepiece.SentencePieceProcessor(model_file=str(sp_model_path))


def test_special_ids_come_from_the_model(sp_model_path):
    tok = PaligemmaTokenizer(sp_model_path, 16)
    assert (tok.bos_id, tok.eos_id, tok.pad_id) == (2, 1, 0)


def test_the_fixture_has_newline_as_one_token(sp):
    """The premise of the format tests below, as in PaliGemma's tokenizer (a property of the fixture, not of
    pi0_jax code)."""
    assert len(sp.encode("\n")) == 1


def test_pi0_format(sp_model_path, sp):
    tok = PaligemmaTokenizer(sp_model_path, 48)
    tokens, mask = tok.tokenize("  pick_up the bowl\nnow ")
    want = [sp.bos_id()] + sp.encode("pick up the bowl now") + sp.encode("\n")
    assert tokens.dtype == np.int32 and mask.dtype == bool and tokens.shape == mask.shape == (48,)
    np.testing.assert_array_equal(tokens[: len(want)], want)
    assert (tokens[len(want):] == 0).all()
    np.testing.assert_array_equal(mask, np.arange(48) < len(want))


def test_no_lowercasing(sp_model_path, sp):
    tokens, mask = PaligemmaTokenizer(sp_model_path, 48).tokenize("Pick Up")
    assert tokens[: mask.sum()].tolist() == [2] + sp.encode("Pick Up") + sp.encode("\n")


def test_state_discretisation_by_hand():
    # Bin i covers [-1 + i/128, -1 + (i+1)/128); below -1 -> -1; the last bin is open above.
    state = np.array([-1.0, -0.999, 0.0, 0.5, 0.99, 1.0, 2.0, -2.0, -1e-9])
    assert discretize_state(state).tolist() == [0, 0, 128, 192, 254, 255, 255, -1, 127]


def test_pi05_format(sp_model_path, sp):
    tok = PaligemmaTokenizer(sp_model_path, 64)
    state = np.array([-1.0, 0.0, 0.5, 2.0])
    text = "Task: pick up the bowl, State: 0 128 192 255;\nAction: "
    assert state_prompt(" pick_up the bowl\n", state) == text
    tokens, mask = tok.tokenize(" pick_up the bowl\n", state)
    want = [2] + sp.encode(text)
    np.testing.assert_array_equal(tokens[: len(want)], want)
    assert mask.sum() == len(want) and not mask[len(want):].any()
    assert sp.decode(tokens[1: len(want)].tolist()) == text


def test_truncation_warns(sp_model_path, caplog):
    tok = PaligemmaTokenizer(sp_model_path, 5)
    full = tok.prompt_ids("pick up the black bowl between the plate and the ramekin")
    with caplog.at_level(logging.WARNING):
        tokens, mask = tok.tokenize("pick up the black bowl between the plate and the ramekin")
    assert "exceeds max length" in caplog.text
    assert tokens.tolist() == full[:5] and mask.all()


def test_prompt_types(sp_model_path):
    tok = PaligemmaTokenizer(sp_model_path, 16)
    ref = tok.tokenize("open the drawer")[0]
    np.testing.assert_array_equal(tok.tokenize(np.array("open the drawer"))[0], ref)
    np.testing.assert_array_equal(tok.tokenize(b"open the drawer")[0], ref)
    with pytest.raises(TypeError):
        tok.tokenize(3)


def test_missing_model_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.model"):
        PaligemmaTokenizer(tmp_path / "nope.model", 8)
