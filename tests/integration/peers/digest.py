"""Digests of decoded payloads, compared across processes for bit-exactness."""

from __future__ import annotations

import hashlib

from co3sop_nodes.v2x.codec import EncodedFeatures, decode_features, decode_labels


def _sha(array) -> str | None:
    return None if array is None else hashlib.sha256(array.tobytes()).hexdigest() + f":{array.dtype}{array.shape}"


def decoded_digest(enc) -> dict:
    if isinstance(enc, EncodedFeatures):
        dec = decode_features(enc)
        return {"features": _sha(dec.features), "confidence": _sha(dec.confidence), "mask": _sha(dec.mask)}
    dec = decode_labels(enc)
    return {"labels": _sha(dec.labels), "confidence": _sha(dec.confidence)}
