"""The head of a text layer, read as text before USD parses anything: how much of a file is read
(HEAD_BYTES) and its layer-metadata block. Used by the cheap scene scan (usd.sniff) and by the
dependency walk's messages (usd.dependencies), which must judge a layer that does not parse."""

from __future__ import annotations

HEAD_BYTES = 16384           # how much of a file the scan reads: a scene layer names its sceneId in its header


def layer_metadata(text: str) -> str | None:
    """The layer-metadata block of a text layer's head (from `(` to its `)`, strings, asset paths and
    comments skipped), "" when the layer has none, None when it does not end within `text`."""
    i, n = text.find("\n") + 1, len(text)
    if i == 0:
        return None
    while i < n:  # whitespace and comments before the block
        if text[i].isspace():
            i += 1
        elif text[i] == "#" or text.startswith("//", i):
            end = text.find("\n", i)
            if end < 0:
                return None
            i = end + 1
        elif text.startswith("/*", i):
            end = text.find("*/", i + 2)
            if end < 0:
                return None
            i = end + 2
        else:
            break
    if i >= n:
        return None
    if text[i] != "(":
        return ""
    depth, j = 0, i
    while j < n:
        c = text[j]
        if c in "\"'@":
            quote = c * 3 if text.startswith(c * 3, j) else c
            k = j + len(quote)
            while k < n and not text.startswith(quote, k):
                k += 2 if text[k] == "\\" and c != "@" else 1
            if k >= n:
                return None
            j = k + len(quote)
            continue
        if c == "#" or text.startswith("//", j):
            end = text.find("\n", j)
            if end < 0:
                return None
            j = end + 1
            continue
        if text.startswith("/*", j):
            end = text.find("*/", j + 2)
            if end < 0:
                return None
            j = end + 2
            continue
        if c == "(":
            depth += 1
        elif c == ")":
            depth -= 1
            if depth == 0:
                return text[i:j + 1]
        j += 1
    return None
