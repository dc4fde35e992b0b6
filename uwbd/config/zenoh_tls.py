"""The TLS material a Zenoh file names, checked as Zenoh will need it: each key and
certificate readable (PEM), the key the certificate's own, the certificate signed by the
file's CA and valid today; and what the certificate's name means for access control (a
router as shipped admits a certificate's puts on ``uwbd/<its common name>/**`` only).

A bad key or certificate would otherwise surface only as a Zenoh session that never starts
(a daemon without Zenoh) or a router that refuses every connection. Read with
``cryptography``, imported here only, for configs that name a Zenoh file.
"""

from __future__ import annotations

import datetime
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# each side's (key, certificate) settings in a Zenoh file's transport.link.tls
PAIRS = {"listen": ("listen_private_key", "listen_certificate"),
         "connect": ("connect_private_key", "connect_certificate")}
CA = "root_ca_certificate"


@dataclass(frozen=True)
class Identity:
    """A side's certificate as checked: its common name, where it was read."""

    side: str
    certificate: str
    common_name: str | None


def check_material(get: Callable[[str], Any], error: Callable[[str], None]
                   ) -> list[Identity]:
    """Every key and certificate ``get(name)`` names (``transport.link.tls.<name>``, files
    only: the ``_base64`` forms are Zenoh's to read), each problem said through ``error``
    with the setting and the file; the identities that passed."""
    from cryptography import x509  # noqa: PLC0415 - only for configs with TLS material
    from cryptography.exceptions import UnsupportedAlgorithm  # noqa: PLC0415
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric.types import (  # noqa: PLC0415
        PrivateKeyTypes,
    )

    def certificate(name: str) -> x509.Certificate | None:
        path = get(name)
        if not isinstance(path, str) or not Path(path).is_file():
            return None  # (said by the caller: no such file)
        data = Path(path).read_bytes()
        try:
            return x509.load_pem_x509_certificate(data)
        except ValueError:
            hint = (" (it holds a private key: are the key and the certificate swapped?)"
                    if b"PRIVATE KEY" in data else "")
            error(f"transport.link.tls.{name} {path}: not a PEM certificate{hint}")
        return None

    def private_key(name: str) -> PrivateKeyTypes | None:
        path = get(name)
        if not isinstance(path, str) or not Path(path).is_file():
            return None
        data = Path(path).read_bytes()
        try:
            return serialization.load_pem_private_key(data, password=None)
        except TypeError:
            error(f"transport.link.tls.{name} {path}: the key is encrypted; Zenoh needs it "
                  "unencrypted (readable by the uwbd user only)")
        except (ValueError, UnsupportedAlgorithm):
            hint = (" (it holds a certificate: are the key and the certificate swapped?)"
                    if b"CERTIFICATE" in data else "")
            error(f"transport.link.tls.{name} {path}: not a PEM private key{hint}")
        return None

    ca = certificate(CA)
    now = datetime.datetime.now(datetime.timezone.utc)
    identities = []
    for side, (key_name, cert_name) in PAIRS.items():
        if _holds(get(key_name), b"CERTIFICATE") and _holds(get(cert_name), b"PRIVATE KEY"):
            error(f"transport.link.tls.{key_name} {get(key_name)} holds a certificate and "
                  f"{cert_name} {get(cert_name)} a key: they are swapped")
            continue
        key, cert = private_key(key_name), certificate(cert_name)
        if cert is None:
            continue
        path = get(cert_name)
        ok = True
        if key is not None and _public(key.public_key()) != _public(cert.public_key()):
            error(f"transport.link.tls.{key_name} {get(key_name)} is not the key of "
                  f"{cert_name} {path}: give the key the certificate was made for")
            ok = False
        if ca is not None and not _issued_by(cert, ca):
            error(f"transport.link.tls.{cert_name} {path} is not signed by {CA} "
                  f"{get(CA)}: the other side refuses it; sign it with that CA, or name the "
                  "CA that signed it")
            ok = False
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            error(f"transport.link.tls.{cert_name} {path} is valid from "
                  f"{cert.not_valid_before_utc:%Y-%m-%d} to {cert.not_valid_after_utc:%Y-%m-%d}"
                  f", not today ({now:%Y-%m-%d}): renew it, or set this machine's clock")
            ok = False
        if ok:
            names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
            identities.append(Identity(side, str(path),
                                       str(names[0].value) if names else None))
    return identities


def _holds(path: Any, marker: bytes) -> bool:
    """The file ``path`` names exists and holds ``marker`` (a PEM block's label)."""
    return isinstance(path, str) and Path(path).is_file() and marker in Path(path).read_bytes()


def _public(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415

    return bytes(key.public_bytes(serialization.Encoding.DER,
                                  serialization.PublicFormat.SubjectPublicKeyInfo))


def _issued_by(cert: Any, ca: Any) -> bool:
    """``cert`` is ``ca``'s own, or signed by it."""
    from cryptography.exceptions import InvalidSignature  # noqa: PLC0415

    if cert == ca:
        return True
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True
