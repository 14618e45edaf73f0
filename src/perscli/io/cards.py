"""FITS header cards: the block and card sizes, reading cards into a :class:`Header`, checking them, writing them.

- :data:`BLOCK`, :data:`CARD` and :func:`padded`: the 2880-byte blocks and
  80-character cards every FITS file is made of.
- :func:`_parse_value` and :class:`Header`: the values of stored cards
  (fixed and free format, the CONTINUE long-string convention).
- :func:`_card_problem` and :func:`_check_cards`: what FITS allows in a card,
  so that a header with an invalid card is refused as it is read (and never
  copied into an output).
- :func:`format_card`, :func:`history_cards`: card images for outputs, and
  :func:`_is_structural`: the keywords the writer sets itself.

Part of the FITS layer whose writer is :mod:`perscli.io.fitsfile`.
"""

from __future__ import annotations

import math
import re

import numpy as np

from .. import PerscliError

BLOCK = 2880
CARD = 80


def padded(n: int) -> int:
    return (n + BLOCK - 1) // BLOCK * BLOCK


# -- header values ------------------------------------------------------------------------------

def _parse_value(text: str):
    """Value of a fixed- or free-format card field (after '= ')."""
    s = text.lstrip()
    if not s:
        return None, ""
    if s[0] == "'":
        out = []
        i = 1
        n = len(s)
        while i < n:
            j = s.find("'", i)
            if j < 0:
                out.append(s[i:])
                i = n
                break
            out.append(s[i:j])
            if j + 1 < n and s[j + 1] == "'":
                out.append("'")
                i = j + 2
                continue
            i = j
            break
        rest = s[i + 1:]
        comment = rest.split("/", 1)[1].strip() if "/" in rest else ""
        return "".join(out).rstrip(), comment
    token, _, comment = s.partition("/")
    token = token.strip()
    comment = comment.strip()
    if token == "T":
        return True, comment
    if token == "F":
        return False, comment
    if token == "":
        return None, comment
    try:
        return int(token), comment
    except ValueError:
        pass
    try:
        return float(token.replace("D", "E").replace("d", "e")), comment
    except ValueError:
        return token, comment  # complex or non-standard: kept as text


class Header:
    """Parsed cards of one HDU: a read-only mapping plus the card images.

    Long strings (the CONTINUE convention) are joined in linear time, so a
    header of 100,000 CONTINUE cards is parsed in a fraction of a second.

    Attributes
    ----------
    cards : list of str
        The 80-character card images as found (END excluded).
    """

    def __init__(self, cards):
        self.cards = [c.ljust(CARD)[:CARD] for c in cards]
        self._values = {}
        self._history = []
        pending, pieces = None, []

        def flush():
            if pending is not None and len(pieces) > 1:
                self._values[pending] = "".join(pieces)

        for card in self.cards:
            key = card[:8].rstrip()
            if key == "CONTINUE" and pending is not None:
                more, _ = _parse_value(card[8:])
                if isinstance(more, str):
                    if pieces[-1].endswith("&"):
                        pieces[-1] = pieces[-1][:-1]
                    pieces.append(more)
                    if not more.endswith("&"):
                        flush()
                        pending, pieces = None, []
                    continue
            flush()
            pending, pieces = None, []
            if key in ("HISTORY", "COMMENT", ""):
                if key == "HISTORY":
                    self._history.append(card[8:].rstrip())
                continue
            if key == "HIERARCH" and "=" in card:
                name, _, rest = card[9:].partition("=")
                key = name.strip()
                value, _ = _parse_value(rest)
            elif card[8:10] == "= ":
                value, _ = _parse_value(card[10:])
            else:
                continue
            if key not in self._values:  # the first occurrence wins, as in astropy
                self._values[key] = value
                if isinstance(value, str) and value.endswith("&"):
                    pending, pieces = key, [value]
        flush()

    def __contains__(self, key):
        return key in self._values

    def __getitem__(self, key):
        return self._values[key]

    def get(self, key, default=None):
        return self._values.get(key, default)

    def keys(self):
        return self._values.keys()

    @property
    def history(self) -> list:
        return list(self._history)


# -- header cards as FITS allows them ---------------------------------------------------------------

_KEYWORD = re.compile(rb"[A-Z0-9_-]* *")
_NUMBER = rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[EeDd][+-]?\d+)?"
#: a fixed- or free-format value (FITS Standard 4.2): string, logical, number, complex, or none; then a comment
_VALUE = re.compile(rb" *(?:'(?:[^']|'')*'|[TF]|" + _NUMBER + rb"|\( *" + _NUMBER + rb" *, *" + _NUMBER
                    + rb" *\))? *(?:/.*)?")
_STRING = re.compile(rb" *(?:'(?:[^']|'')*')? *(?:/.*)?")
_PRINTABLE = bytes(range(0x20, 0x7F))


def _card_problem(card: bytes) -> str | None:
    """What makes one 80-byte card invalid FITS (None when it is valid)."""
    if card.translate(None, _PRINTABLE):
        bad = next(b for b in card if b < 0x20 or b > 0x7E)
        return f"holds the byte {bad:#04x}, which is not printable ASCII text"
    key = card[:8]
    if key == b"HIERARCH":
        if b"=" in card[8:] and not _VALUE.fullmatch(card[8:].split(b"=", 1)[1]):
            return "has a value that is not a FITS value (an unterminated string, or text that is no number)"
        return None
    if not _KEYWORD.fullmatch(key):
        return "has a keyword name with characters FITS does not allow (A-Z, 0-9, - and _)"
    if key == b"CONTINUE":
        return None if _STRING.fullmatch(card[8:]) else "continues a string without a valid string value"
    if card[8:10] == b"= " and key.rstrip() not in (b"COMMENT", b"HISTORY", b""):
        if not _VALUE.fullmatch(card[10:]):
            return "has a value that is not a FITS value (an unterminated string, or text that is no number)"
    return None


def _check_cards(raw: bytes, where: str) -> None:
    """Refuse a header (its stored bytes, END included) holding a card that is not valid FITS.

    Such cards would be copied into outputs that other readers refuse
    (astropy: 'Card is not FITS standard'), and text with control
    characters breaks the libraries a header is given to (WCS).
    """
    for i in range(0, len(raw) - CARD + 1, CARD):
        card = raw[i:i + CARD]
        if card[:8] == b"END     ":
            return
        problem = _card_problem(card)
        if problem is not None:
            # control characters shown escaped: a BEL or an ESC in the message would ring or redraw the terminal
            text = "".join(ch if " " <= ch <= "~" else f"\\x{ord(ch):02x}" for ch in card.decode("latin-1")).rstrip()
            shown = text if len(text) <= 40 else text[:40] + "..."
            raise PerscliError(f"{where}: card {i // CARD + 1} ({shown}) {problem}: the header is corrupt; "
                               "re-copy the file or fix the card")


# -- writing -------------------------------------------------------------------------------------

def _format_value(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return f"{'T' if value else 'F':>20}"
    if isinstance(value, (int, np.integer)):
        return f"{int(value):>20}"
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"FITS cannot store the non-finite value {value}")
        text = repr(value).upper()
        if "." not in text and "E" not in text:
            text += ".0"
        elif "E" in text and "." not in text.split("E")[0]:
            mant, exp = text.split("E")
            text = f"{mant}.0E{exp}"
        return f"{text:>20}"
    text = _ascii_text(str(value)).replace("'", "''")
    # fixed format: the closing quote at column 20 or later, as astropy and cfitsio write it
    quoted = f"'{text:<8}'"
    return f"{quoted:<20}"


def _ascii_text(text: str) -> str:
    """``text`` as printable ASCII, the only characters a FITS header holds: others are escaped
    (``é`` becomes ``\\xe9``, a tab ``\\t``), so that a file name or a message of any script can
    be recorded without making the header invalid."""
    if text.isascii() and text.isprintable():
        return text
    return "".join(ch if " " <= ch <= "~" else ch.encode("unicode_escape").decode("ascii") for ch in text)


def format_card(key: str, value=None, comment: str | None = None) -> str:
    """``KEY = value / comment`` as one 80-character card image.

    A string too long for one card continues on CONTINUE cards (the FITS
    long-string convention): the result is then several cards' worth of
    characters, a multiple of 80.
    """
    key = key.upper()
    if len(key) > 8:
        raise ValueError(f"keyword {key!r} is longer than 8 characters")
    if key in ("HISTORY", "COMMENT", ""):
        return f"{key:<8}{_ascii_text(str(value or ''))}"[:CARD].ljust(CARD)
    text = _format_value(value)
    if isinstance(value, str) and len(text.rstrip()) > 70:
        return _long_string_cards(key, _ascii_text(value), comment)
    card = f"{key:<8}= {text}"
    if comment:
        card += f" / {_ascii_text(comment)}"
    return card[:CARD].ljust(CARD)


def _long_string_cards(key: str, value: str, comment: str | None) -> str:
    escaped = value.replace("'", "''")
    pieces = []
    while escaped:
        cut = 67
        if len(escaped) > cut and escaped[cut - 1] == "'" and escaped[cut - 2:cut] != "''":
            cut -= 1  # never split an escaped quote pair
        pieces.append(escaped[:cut])
        escaped = escaped[cut:]
    cards = []
    for i, piece in enumerate(pieces):
        last = i == len(pieces) - 1
        body = f"'{piece}{'' if last else '&'}'"
        head = f"{key:<8}= " if i == 0 else "CONTINUE  "
        cards.append(f"{head}{body}".ljust(CARD)[:CARD])
    if comment:
        cards[-1] = (cards[-1].rstrip() + f" / {_ascii_text(comment)}")[:CARD].ljust(CARD)
    return "".join(cards)


def history_cards(text: str) -> list:
    """HISTORY cards carrying ``text``, wrapped at 72 characters."""
    return [format_card("HISTORY", text[i:i + 72]) for i in range(0, max(len(text), 1), 72)]


#: structural and checksum keywords: written by fitsio or by the checksum pass, never copied
_STRUCTURAL = {"SIMPLE", "XTENSION", "BITPIX", "NAXIS", "EXTEND", "PCOUNT", "GCOUNT", "BZERO", "BSCALE",
               "BLANK", "CHECKSUM", "DATASUM", "EXTNAME", "TFIELDS", "THEAP", "ZIMAGE", "ZBITPIX", "ZNAXIS",
               "ZTILE1", "ZTILE2", "ZTILE3", "ZCMPTYPE", "ZQUANTIZ", "ZDITHER0", "ZHECKSUM", "ZDATASUM",
               "ZSIMPLE", "ZEXTEND", "ZTENSION", "ZPCOUNT", "ZGCOUNT", "ZBLANK"}
_STRUCTURAL_PATTERN = re.compile(r"^(NAXIS\d+|ZNAXIS\d+|ZTILE\d+|ZNAME\d+|ZVAL\d+|T(TYPE|FORM|UNIT|DIM|NULL|SCAL|ZERO|DISP)\d+)$")


def _is_structural(key: str) -> bool:
    return key in _STRUCTURAL or _STRUCTURAL_PATTERN.match(key) is not None
