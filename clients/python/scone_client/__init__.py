"""Reference client of the scone service: the client contract's FAST + FREAK extraction and gRPC calls."""

from scone_client.contract import (
    ExtractorConfig,
    Features,
    configure_opencv,
    decode_grey,
    extract,
    extract_encoded,
)

__all__ = ["ExtractorConfig", "Features", "configure_opencv", "decode_grey", "extract", "extract_encoded"]
