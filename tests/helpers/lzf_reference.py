"""An LZF compressor written for the tests, independent of typ's decoder (liblzf's format).

Greedy, as liblzf is: at each position the most recent earlier occurrence of the next 3 bytes
(within 8 KiB) is extended as far as it matches (up to 264 bytes; a match may overlap the bytes
it produces, which a decoder must copy byte by byte), else the byte joins a literal run (at
most 32 bytes each). Tokens: a literal run ``[n - 1] + n bytes``; a back reference of length L
at distance D ``[(L - 2) << 5 | (D - 1) >> 8, (D - 1) & 255]`` for L < 9, else
``[7 << 5 | (D - 1) >> 8, L - 9, (D - 1) & 255]``.
"""
from __future__ import annotations

MAX_DISTANCE = 8192
MAX_LENGTH = 264


def lzf_compress(data: bytes) -> bytes:
    out, literal = bytearray(), bytearray()
    last: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush() -> None:
        for k in range(0, len(literal), 32):
            run = literal[k:k + 32]
            out.append(len(run) - 1)
            out.extend(run)
        literal.clear()

    while i < n:
        key = data[i:i + 3]
        ref = last.get(key) if len(key) == 3 else None
        if len(key) == 3:
            last[key] = i
        if ref is not None and i - ref <= MAX_DISTANCE:
            length, most = 0, min(MAX_LENGTH, n - i)
            while length < most and data[ref + length] == data[i + length]:
                length += 1
            if length >= 3:
                flush()
                distance = i - ref - 1
                if length < 9:
                    out.append((length - 2) << 5 | distance >> 8)
                else:
                    out += bytes([7 << 5 | distance >> 8, length - 9])
                out.append(distance & 0xFF)
                i += length
                continue
        literal.append(data[i])
        i += 1
    flush()
    return bytes(out)
