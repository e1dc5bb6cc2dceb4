"""The codec's errors: every failure on untrusted bytes is a CodecError whose ``reason`` is a
short label fit for a rejection counter."""


class CodecError(ValueError):
    """A message that cannot be encoded or decoded; ``reason`` is a counter label."""

    reason = "codec"


class MessageTooLarge(CodecError):
    """Payload (or encoded message) exceeds the size limit."""

    reason = "too_large"


class MalformedMessage(CodecError):
    """Not msgpack, wrong envelope shape, or a bad object column."""

    reason = "malformed"


class SchemaVersionError(CodecError):
    """Envelope schema version differs from this build's ``SCHEMA_VERSION``."""

    reason = "version"


class WrongMessageType(CodecError):
    """Envelope type tag differs from the expected model's ``TYPE``."""

    reason = "wrong_type"


class InvalidMessage(CodecError):
    """Well-formed envelope whose content breaks a model rule; ``field`` names it."""

    reason = "invalid"

    def __init__(self, message: str, field: str = "") -> None:
        super().__init__(message)
        self.field = field
