"""A small BERT WordPiece tokenizer (uncased), pure Python, reading a standard ``vocab.txt``.

Used for the text side of ONNX open-vocabulary detectors (Grounding-DINO exports take BERT
``input_ids``) and for the offline MiniLM phrase embedder (paper Sec. III-B). It follows
BERT's ``BasicTokenizer`` (lower-casing, accent stripping, whitespace/punctuation splitting, CJK
characters as single tokens) followed by greedy longest-match-first WordPiece with ``##`` continuation
pieces. Every token keeps its character span in the input text so phrase spans can be mapped to token
positions.
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple, Union

__all__ = ["WordPieceTokenizer", "Encoding"]


@dataclass
class Encoding:
    """Result of :meth:`WordPieceTokenizer.encode`.

    Attributes:
        ids: token ids including ``[CLS]`` first and ``[SEP]`` last (length L).
        tokens: the token strings (length L).
        offsets: (start, end) character span of each token in the input text; (0, 0) for special tokens.
    """

    ids: List[int]
    tokens: List[str]
    offsets: List[Tuple[int, int]]


def _is_punct(ch: str) -> bool:
    cp = ord(ch)
    if 33 <= cp <= 47 or 58 <= cp <= 64 or 91 <= cp <= 96 or 123 <= cp <= 126:
        return True
    return unicodedata.category(ch).startswith("P")


def _is_cjk(cp: int) -> bool:
    return (
        0x4E00 <= cp <= 0x9FFF or 0x3400 <= cp <= 0x4DBF or 0x20000 <= cp <= 0x2A6DF
        or 0x2A700 <= cp <= 0x2B73F or 0x2B740 <= cp <= 0x2B81F or 0x2B820 <= cp <= 0x2CEAF
        or 0xF900 <= cp <= 0xFAFF or 0x2F800 <= cp <= 0x2FA1F
    )


class WordPieceTokenizer:
    """Uncased BERT WordPiece tokenizer.

    Args:
        vocab: path to a ``vocab.txt`` (one token per line, the line number is the id) or a
            ``{token: id}`` dict.
        lowercase: lower-case and strip accents (BERT uncased models).
        max_chars_per_word: longer words become ``[UNK]``.

    Raises:
        FileNotFoundError: the vocab file does not exist.
        ValueError: the vocab lacks ``[CLS]``, ``[SEP]``, ``[PAD]`` or ``[UNK]``.
    """

    def __init__(self, vocab: Union[str, Path, Dict[str, int]], lowercase: bool = True,
                 max_chars_per_word: int = 100) -> None:
        if isinstance(vocab, dict):
            self.vocab = dict(vocab)
        else:
            p = Path(vocab)
            if not p.is_file():
                raise FileNotFoundError(f"tokenizer vocab not found: {p}")
            with open(p, "r", encoding="utf-8") as f:
                self.vocab = {line.rstrip("\n"): i for i, line in enumerate(f)}
        for tok in ("[CLS]", "[SEP]", "[PAD]", "[UNK]"):
            if tok not in self.vocab:
                raise ValueError(f"vocab has no {tok} token")
        self.lowercase = lowercase
        self.max_chars_per_word = int(max_chars_per_word)
        self.cls_id = self.vocab["[CLS]"]
        self.sep_id = self.vocab["[SEP]"]
        self.pad_id = self.vocab["[PAD]"]
        self.unk_id = self.vocab["[UNK]"]

    # ------------------------------------------------------------------------------------------
    def _basic(self, text: str) -> List[Tuple[str, int, int]]:
        """Split into words and punctuation with character spans (BERT BasicTokenizer)."""
        words: List[Tuple[str, int, int]] = []
        cur: List[str] = []
        start = 0

        def flush(end: int) -> None:
            if cur:
                words.append(("".join(cur), start, end))
                cur.clear()

        for i, ch in enumerate(text):
            cp = ord(ch)
            if cp == 0 or cp == 0xFFFD or (unicodedata.category(ch).startswith("C") and ch not in "\t\n\r"):
                continue
            if ch.isspace():
                flush(i)
                continue
            if _is_punct(ch) or _is_cjk(cp):
                flush(i)
                words.append((ch, i, i + 1))
                continue
            if self.lowercase:
                ch = ch.lower()
                ch = "".join(c for c in unicodedata.normalize("NFD", ch) if unicodedata.category(c) != "Mn")
            if not cur:
                start = i
            cur.append(ch)
        flush(len(text))
        return words

    def _wordpiece(self, word: str) -> List[str]:
        if len(word) > self.max_chars_per_word:
            return ["[UNK]"]
        pieces: List[str] = []
        i = 0
        while i < len(word):
            j = len(word)
            found = None
            while j > i:
                sub = word[i:j] if i == 0 else "##" + word[i:j]
                if sub in self.vocab:
                    found = sub
                    break
                j -= 1
            if found is None:
                return ["[UNK]"]
            pieces.append(found)
            i = j
        return pieces

    def encode(self, text: str, max_length: int = 512) -> Encoding:
        """Tokenise ``text`` into ``[CLS] ... [SEP]``, truncated to ``max_length`` tokens in total.

        Returns:
            :class:`Encoding` with ids, tokens and character offsets.

        Raises:
            ValueError: ``max_length < 2``.
        """
        if max_length < 2:
            raise ValueError(f"max_length must be >= 2, got {max_length}")
        tokens, ids, offs = ["[CLS]"], [self.cls_id], [(0, 0)]
        for word, s, e in self._basic(text):
            pieces = self._wordpiece(word)
            if pieces == ["[UNK]"]:
                spans = [(s, e)]
            else:
                spans, pos = [], s
                for p in pieces:
                    n = len(p) - 2 if p.startswith("##") else len(p)
                    spans.append((pos, min(e, pos + n)))
                    pos += n
            for p, sp in zip(pieces, spans):
                if len(tokens) >= max_length - 1:
                    break
                tokens.append(p)
                ids.append(self.vocab.get(p, self.unk_id))
                offs.append(sp)
        tokens.append("[SEP]")
        ids.append(self.sep_id)
        offs.append((0, 0))
        return Encoding(ids=ids, tokens=tokens, offsets=offs)
