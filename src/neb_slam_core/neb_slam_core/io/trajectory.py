"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

Readable and written in the format the TUM benchmark tools (and evo) use.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..geometry.se3 import is_rigid, pose_from_tum, pose_to_tum

log = logging.getLogger(__name__)


@dataclass
class Trajectory:
    """Stamped camera-to-world poses.

    Attributes:
        stamps_ns: ``(N,)`` int64 nanoseconds, increasing.
        poses: ``(N, 4, 4)`` float64 ``T_world_cam``.
    """

    stamps_ns: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps_ns) != len(self.poses):
            raise ValueError(f"Trajectory: {len(self.stamps_ns)} stamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    @property
    def stamps_s(self) -> np.ndarray:
        return self.stamps_ns.astype(np.float64) * 1e-9

    @classmethod
    def of_frames(cls, frames) -> Trajectory:
        """The ground truth that ``frames`` (:class:`~neb_slam_core.types.RgbdFrame`) carry: the stamp and
        ``T_world_cam`` of each frame that has a pose."""
        posed = [f for f in frames if f.T_world_cam is not None]
        return cls(np.array([f.stamp_ns for f in posed], dtype=np.int64), np.array([f.T_world_cam for f in posed]))


def stamp_s_to_ns(text_or_float) -> int:
    """Seconds (as text like ``'1305031102.160407'`` or a float) -> integer nanoseconds, exactly for text."""
    if isinstance(text_or_float, str):
        whole, _, frac = text_or_float.strip().partition(".")
        frac = (frac + "000000000")[:9]
        sign = -1 if whole.startswith("-") else 1
        return int(whole) * 1_000_000_000 + sign * int(frac)
    return int(round(float(text_or_float) * 1e9))


def stamp_ns_to_text(stamp_ns: int) -> str:
    """Integer nanoseconds -> ``'seconds.fraction'`` with 9 decimals, exact."""
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def read_tum_trajectory(path: str | Path, skip_bad_lines: bool = False) -> Trajectory:
    """Read a TUM-format trajectory file.

    A line is bad when it does not hold 8 numbers (commas count as separators), when its timestamp is
    not a plain decimal number of seconds, or when its pose is not finite or its quaternion is not of
    unit length (within 1e-2; it is then normalised). By default the first bad line raises
    :class:`DatasetError` naming the file and the line: an estimate must be read back whole. With
    ``skip_bad_lines`` (ground truth, which only evaluation and the first pose use) bad lines are left
    out with one warning naming their line numbers.

    The file is checked as a whole with array operations (:func:`_parse_tum_rows`), so that a
    ground-truth file of tens of thousands of lines costs no Python work per line.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "trajectory file not found (expected 'timestamp tx ty tz qx qy qz qw' lines)")
    rows = _parse_tum_rows(path.read_text())
    bad = np.flatnonzero(rows.problem != _OK)
    if len(bad) and not skip_bad_lines:
        raise DatasetError(path, f"line {rows.lineno[bad[0]]}: {rows.describe(bad[0])}")
    if len(bad):
        shown = ", ".join(str(n) for n in rows.lineno[bad[:_MAX_NAMED_LINES]])
        more = f" and {len(bad) - _MAX_NAMED_LINES} more" if len(bad) > _MAX_NAMED_LINES else ""
        log.warning(
            "%s: skipped %d bad line%s (%s%s; line %d: %s); the other %d poses are used",
            path,
            len(bad),
            "" if len(bad) == 1 else "s",
            shown,
            more,
            rows.lineno[bad[0]],
            rows.describe(bad[0]),
            len(rows.lineno) - len(bad),
        )
    good = rows.problem == _OK
    values = rows.values[good]
    values[:, 3:] /= np.linalg.norm(values[:, 3:], axis=1, keepdims=True)
    return Trajectory(rows.stamps_ns[good], pose_from_tum(values) if len(values) else np.zeros((0, 4, 4)))


# ----------------------------------------------------------------------------------------------
# vectorised parsing of TUM trajectory text

#: what is wrong with a data line (``_OK``: nothing)
_OK, _FIELD_COUNT, _NOT_A_NUMBER, _BAD_STAMP, _NOT_FINITE, _NOT_UNIT = range(6)
#: bad lines named one by one in the warning of ``skip_bad_lines``; the rest are counted
_MAX_NAMED_LINES = 20
#: largest whole number of seconds whose nanoseconds (plus a fraction) fit in int64
_MAX_STAMP_S = (np.iinfo(np.int64).max - 999_999_999) // 1_000_000_000

# Character classes of the text's UTF-8 bytes. Separators (whitespace and commas) and the newline split
# tokens; every other byte belongs to a token (bytes of non-ASCII characters are _OTHER). Only digits,
# one point, signs and one exponent make a number.
_SEP, _NEWLINE, _DIGIT, _POINT, _SIGN, _EXP, _HASH, _OTHER = range(8)
_SEPARATORS = " \t\v\f\x1c\x1d\x1e\x1f,"  # the ASCII whitespace of str.split(), and the comma
_TOKEN_RE = re.compile(r"[^ \t\v\f\x1c-\x1f,\n]+")  # the tokens, in the same order as the classes find them
#: Python's spellings of non-finite floats: a field holding one is a non-finite pose, not a non-number
_NON_FINITE = ("nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity")


def _byte_classes() -> np.ndarray:
    """``(256,)`` class of each byte value."""
    table = np.full(256, _OTHER, dtype=np.uint8)
    classes = {_SEP: _SEPARATORS, _NEWLINE: "\n", _DIGIT: "0123456789", _POINT: ".", _SIGN: "+-", _EXP: "eE"}
    for c, chars in {**classes, _HASH: "#"}.items():
        table[[ord(ch) for ch in chars]] = c
    return table


_BYTE_CLASS = _byte_classes()


@dataclass
class _TumRows:
    """Every data line (not empty, not a ``#`` comment) of a TUM trajectory text.

    Attributes:
        lineno: ``(N,)`` 1-based line numbers.
        problem: ``(N,)`` what is wrong with each line (``_OK`` and the codes above).
        stamps_ns: ``(N,)`` int64 stamps (0 where the line is bad).
        values: ``(N, 7)`` ``tx ty tz qx qy qz qw`` as read (NaN where the line is bad).
        n_tokens: ``(N,)`` fields per line; ``lines``: the text's lines, for messages.
    """

    lineno: np.ndarray
    problem: np.ndarray
    stamps_ns: np.ndarray
    values: np.ndarray
    n_tokens: np.ndarray
    lines: list[str]

    def describe(self, k: int) -> str:
        """What is wrong with data line ``k``, for a message."""
        line = self.lines[self.lineno[k] - 1].strip()
        code = self.problem[k]
        if code == _FIELD_COUNT:
            return f"expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {self.n_tokens[k]}"
        if code == _NOT_A_NUMBER:
            return f"not a number in {line!r}"
        if code == _BAD_STAMP:
            return f"timestamp in {line!r} is not a decimal number of seconds within the int64 nanosecond range"
        if code == _NOT_FINITE:
            return f"pose is not finite in {line!r}"
        q_norm = float(np.linalg.norm(self.values[k, 3:]))
        return f"quaternion is not unit length (|q| = {q_norm:.4f}) in {line!r}"


def _parse_tum_rows(text: str) -> _TumRows:
    """Parse and check every line of a TUM trajectory text with array operations over its bytes.

    Each byte gets a class; tokens are the runs between separators, lines the runs between newlines.
    Per token, counts of those classes, where its point and exponent are and the neighbours of the
    exponent decide whether it is a decimal number, ``[+-]digits[.digits][(e|E)[+-]digits]`` with digits on at least
    one side of the point; ``nan`` and ``inf`` spellings count as numbers that are not finite. A
    timestamp must be a plain ``[+-]digits[.digits]`` of at most 10 whole digits and is read exactly
    into nanoseconds. The checked fields are converted by Python's float parser in one array call.
    """
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    cls = _BYTE_CLASS[np.frombuffer(text.encode("utf-8"), dtype=np.uint8)]
    n = len(cls)
    in_token = cls >= _DIGIT
    starts = np.flatnonzero(in_token & ~np.concatenate([[False], in_token[:-1]]))
    ends = np.flatnonzero(in_token & ~np.concatenate([in_token[1:], [False]])) + 1

    def shifted(mask: np.ndarray, by: int) -> np.ndarray:
        """``mask`` moved ``by`` bytes to the right (positive) or left (negative), padded with False."""
        out = np.zeros_like(mask)
        if by > 0:
            out[by:] = mask[: len(mask) - by]
        else:
            out[: len(mask) + by] = mask[-by:]
        return out

    def where_in_tokens(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The positions of the (token) bytes of ``mask`` and the token each lies in. These masks are
        sparse (points, signs, exponents), so this is cheaper than a sum over every byte."""
        at = np.flatnonzero(mask)
        return at, np.searchsorted(starts, at, side="right") - 1

    def count(mask: np.ndarray) -> np.ndarray:
        return np.bincount(where_in_tokens(mask)[1], minlength=len(starts))

    def first(mask: np.ndarray) -> np.ndarray:
        """Position of each token's first byte of ``mask``; the token's end where it has none."""
        at, token = where_in_tokens(mask)
        out = ends.copy()
        out[token[::-1]] = at[::-1]  # the last write wins: the first occurrence
        return out

    is_digit, is_point, is_sign, is_exp = (cls == _DIGIT), (cls == _POINT), (cls == _SIGN), (cls == _EXP)
    n_other = count((cls == _OTHER) | (cls == _HASH))
    n_exp, n_point = count(is_exp), count(is_point)
    # digits are dense: summed over each token's segment (to the next token's start; separators hold 0)
    n_digit = np.add.reduceat(is_digit, starts, dtype=np.int64) if len(starts) else np.zeros(0, np.int64)
    point_at, exp_at = first(is_point), first(is_exp)
    sign_ok = np.zeros(n, dtype=bool)
    sign_ok[starts] = True
    misplaced_sign = count(is_sign & ~sign_ok & ~shifted(is_exp, 1))
    # an exponent follows a digit (or a point after a digit) and is followed by [sign] digit
    exp_ok = count(
        is_exp
        & (shifted(is_digit, 1) | (shifted(is_point, 1) & shifted(is_digit, 2)))
        & (shifted(is_digit, -1) | (shifted(is_sign, -1) & shifted(is_digit, -2)))
    )
    is_number = (
        (n_other == 0)
        & (n_exp <= 1)
        & (n_point <= 1)
        & (misplaced_sign == 0)
        & (n_digit > 0)
        & (exp_ok == n_exp)
        & ((n_point == 0) | (n_exp == 0) | (point_at < exp_at))
    )
    whole_digits = point_at - starts - is_sign[starts]  # of a number without exponent

    # lines: a comment's first token starts with '#'
    n_lines = len(lines)
    tok_line = np.searchsorted(np.flatnonzero(cls == _NEWLINE), starts)  # 0-based line of each token
    n_tokens = np.bincount(tok_line, minlength=n_lines)
    first_tok = np.searchsorted(tok_line, np.arange(n_lines))
    has_tokens = n_tokens > 0
    comment = np.zeros(n_lines, dtype=bool)
    comment[has_tokens] = cls[starts[first_tok[has_tokens]]] == _HASH
    data = np.flatnonzero(has_tokens & ~comment)

    problem = np.where(n_tokens[data] == 8, _OK, _FIELD_COUNT).astype(np.int8)
    eight = np.flatnonzero(problem == _OK)
    stamps_ns = np.zeros(len(data), dtype=np.int64)
    values = np.full((len(data), 7), np.nan)
    if len(eight):
        idx = first_tok[data[eight]][:, None] + np.arange(8)  # token indices of the 8-field lines
        # str.split() separates at the same bytes when the text is ASCII (and is faster than the regex)
        split = text.replace(",", " ").split() if text.isascii() else _TOKEN_RE.findall(text)
        tokens = np.array(split, dtype=object)
        field_ok = is_number[idx[:, 1:]]
        odd = np.flatnonzero(~field_ok)  # usually none: the spelling check runs on these only
        field_ok.flat[odd] = np.isin(np.char.lower(tokens[idx[:, 1:]].flat[odd].astype(str)), _NON_FINITE)
        stamp = idx[:, 0]
        stamp_ok = is_number[stamp] & (n_exp[stamp] == 0) & (whole_digits[stamp] > 0) & (whole_digits[stamp] <= 10)
        sub = np.full(len(idx), _OK, dtype=np.int8)
        sub[~field_ok.all(axis=1)] = _NOT_A_NUMBER
        sub[(sub == _OK) & ~stamp_ok] = _BAD_STAMP
        readable = np.flatnonzero(sub == _OK)
        rows = idx[readable]
        vals = tokens[rows[:, 1:]].astype(np.float64)
        ns, in_range = _stamps_to_ns(tokens[rows[:, 0]])
        finite = np.isfinite(vals).all(axis=1)
        unit = finite & (np.abs(np.linalg.norm(vals[:, 3:], axis=1) - 1.0) <= 1e-2)
        sub[readable[~in_range]] = _BAD_STAMP
        sub[readable[in_range & ~finite]] = _NOT_FINITE
        sub[readable[in_range & finite & ~unit]] = _NOT_UNIT
        stamps_ns[eight[readable]] = ns
        values[eight[readable]] = vals
        problem[eight] = sub
    return _TumRows(data + 1, problem, stamps_ns, values, n_tokens[data], lines)


def _stamps_to_ns(tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Checked ``[+-]digits[.digits]`` second texts -> (int64 nanoseconds, whether each is in range).

    Exact: the whole seconds and the first nine fractional digits are read as integers, as
    :func:`stamp_s_to_ns` does for one stamp.
    """
    text = tokens.astype(np.dtypes.StringDType())
    negative = np.strings.startswith(text, "-")
    signed = negative | np.strings.startswith(text, "+")
    body = np.where(signed, np.strings.slice(text, 1, None), text)
    whole, _, frac = np.strings.partition(body, np.array(".", dtype=text.dtype))
    whole_s = whole.astype(np.int64)
    in_range = whole_s <= _MAX_STAMP_S
    frac_ns = np.strings.slice(np.strings.ljust(frac, 9, "0"), 0, 9).astype(np.int64)
    ns = np.where(in_range, whole_s, 0) * 1_000_000_000 + frac_ns
    return np.where(negative, -ns, ns), in_range


def write_tum_trajectory(path: str | Path, traj: Trajectory, header: str | None = None) -> None:
    """Write ``traj`` as a TUM-format file (stamps with 9 decimals, poses with 8)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# {header}"] if header else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for stamp, row in zip(traj.stamps_ns, pose_to_tum(traj.poses) if len(traj) else []):
        lines.append(stamp_ns_to_text(int(stamp)) + " " + " ".join(f"{v:.8f}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def check_rigid_pose(T: np.ndarray, source: str | Path, what: str) -> np.ndarray:
    """Return ``T`` as float64 4x4 or raise :class:`DatasetError` saying it is not a rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatasetError(source, f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not is_rigid(T):
        raise DatasetError(
            source,
            f"{what}: not a rigid transform (rotation part is not orthonormal with det 1, "
            f"or last row is not 0 0 0 1):\n{np.array2string(T, precision=4)}",
        )
    return T
