"""Signed V2X messages (IEEE 1609.2 / ETSI TS 103 097 style): a site PKI, signed envelopes and their verifier.

Pure: no Zenoh, no clock reads (times are arguments). Modules: :mod:`.algorithms` (ECDSA P-256,
Ed25519), :mod:`.certificates` (certificates, revocation lists), :mod:`.pki` (the directory the CA
writes and services load), :mod:`.site` (a whole site's material), :mod:`.envelope` (sign / verify),
:mod:`.replay_window`, :mod:`.trust_reload` (a new revocation list while a service runs),
:mod:`.attacker_keys` (the keys ``v2i attack`` holds), :mod:`.tls` (X.509 for Zenoh TLS).
"""
