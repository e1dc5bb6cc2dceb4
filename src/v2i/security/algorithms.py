"""Signature schemes of v2i: ECDSA P-256 (IEEE 1609.2 / ETSI TS 103 097) and Ed25519.

Both give a 64-byte signature on the wire: P-256 as raw ``r || s`` (32 B each, big-endian, as
1609.2's ``EcdsaP256Signature`` without the point-type tag), Ed25519 natively. Public keys on the
wire: P-256 as a 33-byte compressed point (SEC 1), Ed25519 as its 32 raw bytes. The messages are
hashed with SHA-256 inside ECDSA (``ecdsaWithSHA256``) and with SHA-512 inside Ed25519.

Everything here wraps the ``cryptography`` library (OpenSSL); nothing is hand-rolled.
"""

from __future__ import annotations

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature, encode_dss_signature

P256 = "p256"
ED25519 = "ed25519"
ALGORITHMS = (P256, ED25519)
SIGNATURE_BYTES = 64
PUBLIC_KEY_BYTES = {P256: 33, ED25519: 32}
_P256_COORD_BYTES = 32
_ECDSA = ec.ECDSA(hashes.SHA256())

PrivateKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey
PublicKey = ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey


def check_algorithm(algorithm: str) -> str:
    """``algorithm`` unchanged if it is one of :data:`ALGORITHMS`, else ValueError."""
    if algorithm not in ALGORITHMS:
        raise ValueError(f"unknown signature algorithm {algorithm!r}: expected one of {', '.join(ALGORITHMS)}")
    return algorithm


def generate(algorithm: str) -> PrivateKey:
    """A fresh private key of ``algorithm`` (from the OS's CSPRNG, via OpenSSL)."""
    if check_algorithm(algorithm) == P256:
        return ec.generate_private_key(ec.SECP256R1())
    return ed25519.Ed25519PrivateKey.generate()


def algorithm_of(key: PrivateKey | PublicKey) -> str:
    """The algorithm name of a private or public key; ValueError for any other key type."""
    if isinstance(key, (ec.EllipticCurvePrivateKey, ec.EllipticCurvePublicKey)):
        if not isinstance(key.curve, ec.SECP256R1):
            raise ValueError(f"unsupported curve {key.curve.name}: only P-256 (secp256r1)")
        return P256
    if isinstance(key, (ed25519.Ed25519PrivateKey, ed25519.Ed25519PublicKey)):
        return ED25519
    raise ValueError(f"unsupported key type {type(key).__name__}")


def public_bytes(key: PrivateKey | PublicKey) -> bytes:
    """The wire form of the public half of ``key`` (33 B compressed P-256 point or 32 B Ed25519)."""
    public = key.public_key() if hasattr(key, "private_bytes") else key
    if algorithm_of(public) == P256:
        return public.public_bytes(serialization.Encoding.X962, serialization.PublicFormat.CompressedPoint)
    return public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def load_public(algorithm: str, data: bytes) -> PublicKey:
    """Public key from its wire form; ValueError if ``data`` is not a valid key of ``algorithm``
    (a P-256 point is checked to lie on the curve)."""
    if len(data) != PUBLIC_KEY_BYTES[check_algorithm(algorithm)]:
        raise ValueError(f"{algorithm} public key must be {PUBLIC_KEY_BYTES[algorithm]} bytes, got {len(data)}")
    if algorithm == P256:
        return ec.EllipticCurvePublicKey.from_encoded_point(ec.SECP256R1(), data)
    return ed25519.Ed25519PublicKey.from_public_bytes(data)


def sign(key: PrivateKey, data: bytes) -> bytes:
    """64-byte signature of ``data``: raw ``r || s`` for P-256, native for Ed25519."""
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return key.sign(data)
    r, s = decode_dss_signature(key.sign(data, _ECDSA))
    return r.to_bytes(_P256_COORD_BYTES, "big") + s.to_bytes(_P256_COORD_BYTES, "big")


def verify(key: PublicKey, signature: bytes, data: bytes) -> bool:
    """True iff ``signature`` (64 B) is ``key``'s signature of ``data``; never raises on bad input."""
    if len(signature) != SIGNATURE_BYTES:
        return False
    try:
        if isinstance(key, ed25519.Ed25519PublicKey):
            key.verify(signature, data)
        else:
            r = int.from_bytes(signature[:_P256_COORD_BYTES], "big")
            s = int.from_bytes(signature[_P256_COORD_BYTES:], "big")
            if r == 0 or s == 0:
                return False
            key.verify(encode_dss_signature(r, s), data, _ECDSA)
    except InvalidSignature:
        return False
    return True


def private_pem(key: PrivateKey) -> bytes:
    """PKCS#8 PEM of ``key``, unencrypted (the file's mode 0600 protects it)."""
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def load_private_pem(data: bytes) -> PrivateKey:
    """Private key from PKCS#8 PEM; ValueError if it is not a P-256 or Ed25519 key."""
    key = serialization.load_pem_private_key(data, password=None)
    algorithm_of(key)
    return key
