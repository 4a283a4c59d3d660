"""The OpenIGTLink codec of the live loop: it lives in :mod:`ivc.igtl`, shared with collection (``ivc serve``,
``igtl://`` sources); these names are kept here for the code that imports them from ``ivc.live.igtl``."""

from ivc.igtl import (
    BODY_LIMITS,
    BODY_TIMEOUT_S,
    DEFAULT_PORT,
    HEADER,
    HEADER_SIZE,
    MAX_BODY,
    Frame,
    Framer,
    NDArrayMessage,
    TrackingDataMessage,
    decode_ndarray,
    decode_transform,
    encode_transforms,
    parse_url,
)

__all__ = ["BODY_LIMITS", "BODY_TIMEOUT_S", "DEFAULT_PORT", "HEADER", "HEADER_SIZE", "MAX_BODY", "Frame", "Framer",
           "NDArrayMessage", "TrackingDataMessage", "decode_ndarray", "decode_transform", "encode_transforms",
           "parse_url"]
