"""The package's root exception and its few subclasses.

Every error the core raises on bad input derives from `Co3sopError`, so a
command-line tool or node can catch one type, print its message (which names
the file, topic or field at fault) and never show a traceback.
"""


class Co3sopError(Exception):
    """Root of every error raised by co3sop_nodes on bad input or data."""


class GridError(Co3sopError):
    """A voxel grid specification is invalid (non-positive size, non-finite origin...)."""


class CodecError(Co3sopError):
    """A payload cannot be encoded or decoded."""


class UnknownCodecError(CodecError):
    """The named codec or dtype is not one this version knows."""


class CorruptPayloadError(CodecError):
    """A compressed payload is truncated or corrupt."""


class SizeMismatchError(CodecError):
    """A payload's (declared) size does not match the grid it claims to fill."""


class PayloadTooLargeError(CodecError):
    """A payload declares more uncompressed bytes than the receiver accepts."""


class NonFiniteError(CodecError):
    """A payload carries NaN or infinite values (features, confidence, quantisation scale/offset)."""


class DatasetError(Co3sopError):
    """A dataset file (OPV2V yaml/PCD/PNG, Co3SOP npz, bag) is missing, malformed or inconsistent."""


def exception_line(exc: BaseException) -> str:
    """The first line of an error's message, bounded: C libraries put whole dumps in theirs."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
