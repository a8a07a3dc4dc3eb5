"""A strict structural check of a received dataset's bytes, before pydicom parses them.

pydicom reads leniently: a value shorter than its declared length is returned short, a
truncated dataset just ends, an undefined length on any element is searched for a
delimiter, and sequences are parsed recursively to any depth. So the raw little-endian
byte stream (explicit or implicit VR) is walked first, iteratively, and refused unless

- every element header and value lies inside the message (no 1 GiB or 4 GiB claims),
  values have even lengths and tags ascend strictly within each dataset (no duplicates);
- undefined lengths appear only on sequences and their items, every one delimited, and on
  the top-level Pixel Data of a compressed transfer syntax, whose fragments must each have a
  length that fits and end in a sequence delimiter;
- sequences nest at most :data:`MAX_DEPTH` deep and there are at most :data:`MAX_ELEMENTS`;
- no command (0000) or file meta (0002) group appears in the dataset.

Only then is the dataset handed to pydicom; the value-level checks follow in
:func:`service.scp.check_instance`.
"""

from __future__ import annotations

import struct

from pydicom.datadict import dictionary_VR

__all__ = ["DatasetError", "check_dataset_bytes", "MAX_DEPTH", "MAX_ELEMENTS"]

MAX_DEPTH = 8  # X-ray objects nest sequences 2-3 deep
MAX_ELEMENTS = 20000
UNDEFINED = 0xFFFFFFFF
PIXEL_DATA = 0x7FE00010
ITEM, ITEM_END, SEQUENCE_END = 0xFFFEE000, 0xFFFEE00D, 0xFFFEE0DD
_LONG_VRS = frozenset(b"OB OD OF OL OV OW SQ SV UC UN UR UT UV".split())
_VRS = _LONG_VRS | frozenset(
    b"AE AS AT CS DA DS DT FL FD IS LO LT PN SH SL SS ST TM UI UL US".split())


class DatasetError(ValueError):
    """The dataset's byte stream is malformed; the message says where."""


def _is_sequence(tag: int, vr: bytes | None, length: int) -> bool:
    if vr is not None:
        return vr == b"SQ"
    if length == UNDEFINED:
        return True
    try:
        return dictionary_VR(tag) == "SQ"
    except KeyError:
        return False


def check_dataset_bytes(data: bytes, explicit_vr: bool, encapsulated: bool = False) -> None:
    """Raise :class:`DatasetError` unless ``data`` is a well-formed little-endian dataset
    (``encapsulated``: of a compressed transfer syntax, its Pixel Data in fragments).

    The walk is a loop over an explicit stack of open sequences and items (no recursion),
    so a hostile nesting depth costs nothing before it is refused.
    """
    view = memoryview(data)
    # Open containers: (kind, end offset or None if delimited, last tag seen at this level).
    stack: list[list] = [["dataset", len(data), -1]]
    pos, elements = 0, 0
    while True:
        kind, end, last_tag = stack[-1]
        if end is not None and pos == end:
            stack.pop()
            if not stack:
                return
            continue
        if end is None and pos >= len(data) or end is not None and pos > end:
            raise DatasetError(f"{kind} at depth {len(stack) - 1} runs past the end of the data "
                               f"(offset {pos})")
        if len(data) - pos < 8:
            raise DatasetError(f"truncated element header at offset {pos}")
        group, element = struct.unpack_from("<HH", view, pos)
        tag = group << 16 | element
        if kind == "fragments":  # items of compressed bytes, then the sequence delimiter
            length = struct.unpack_from("<L", view, pos + 4)[0]
            pos += 8
            elements += 1
            if tag == SEQUENCE_END and length == 0:
                stack.pop()
            elif tag != ITEM or length == UNDEFINED or length > len(data) - pos:
                raise DatasetError(f"Pixel Data fragment at offset {pos - 8} is malformed or "
                                   "runs past the end of the data")
            elif elements > MAX_ELEMENTS:
                raise DatasetError(f"more than {MAX_ELEMENTS} elements")
            else:
                pos += length
            continue
        if kind == "sequence":  # only items and the sequence delimiter may appear here
            length = struct.unpack_from("<L", view, pos + 4)[0]
            pos += 8
            if tag == SEQUENCE_END and end is None and length == 0:
                stack.pop()
            elif tag == ITEM:
                if len(stack) > 2 * MAX_DEPTH:
                    raise DatasetError(f"sequences nest deeper than {MAX_DEPTH} levels")
                if length != UNDEFINED and (length > len(data) - pos
                                            or end is not None and pos + length > end):
                    raise DatasetError(f"item at offset {pos - 8} declares {length} bytes, "
                                       "more than remain")
                stack.append(["item", None if length == UNDEFINED else pos + length, -1])
            else:
                raise DatasetError(f"tag ({group:04X},{element:04X}) inside a sequence at offset "
                                   f"{pos - 8} is not an item")
            continue
        if tag == ITEM_END and kind == "item" and end is None:
            if struct.unpack_from("<L", view, pos + 4)[0] != 0:
                raise DatasetError(f"item delimiter at offset {pos} has a non-zero length")
            pos += 8
            stack.pop()
            continue
        if group == 0xFFFE or tag <= last_tag:
            raise DatasetError(f"tag ({group:04X},{element:04X}) at offset {pos} is out of order "
                               "or a stray delimiter")
        if len(stack) == 1 and group in (0x0000, 0x0002):
            raise DatasetError(f"group {group:04X} does not belong in a dataset")
        stack[-1][2] = tag
        elements += 1
        if elements > MAX_ELEMENTS:
            raise DatasetError(f"more than {MAX_ELEMENTS} elements")
        vr = None
        if explicit_vr:
            vr = bytes(view[pos + 4:pos + 6])
            if vr not in _VRS:
                raise DatasetError(f"unknown VR {vr!r} at offset {pos}")
            if vr in _LONG_VRS:
                if len(data) - pos < 12:
                    raise DatasetError(f"truncated element header at offset {pos}")
                length, header = struct.unpack_from("<L", view, pos + 8)[0], 12
            else:
                length, header = struct.unpack_from("<H", view, pos + 6)[0], 8
        else:
            length, header = struct.unpack_from("<L", view, pos + 4)[0], 8
        pos += header
        if _is_sequence(tag, vr, length):
            if length != UNDEFINED and (length > len(data) - pos
                                        or end is not None and pos + length > end):
                raise DatasetError(f"sequence ({group:04X},{element:04X}) declares {length} "
                                   "bytes, more than remain")
            stack.append(["sequence", None if length == UNDEFINED else pos + length, -1])
            continue
        if length == UNDEFINED and encapsulated and tag == PIXEL_DATA and len(stack) == 1:
            stack.append(["fragments", None, -1])
            continue
        if length == UNDEFINED:
            raise DatasetError(f"({group:04X},{element:04X}) has an undefined length (only "
                               "sequences and compressed Pixel Data may)")
        if length % 2:
            raise DatasetError(f"({group:04X},{element:04X}) has an odd length {length}")
        if length > len(data) - pos or end is not None and pos + length > end:
            raise DatasetError(f"({group:04X},{element:04X}) at offset {pos - header} declares "
                               f"{length} bytes, {len(data) - pos} remain")
        pos += length
