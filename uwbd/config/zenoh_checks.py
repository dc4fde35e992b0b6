"""The ``[zenoh]`` table checked: its endpoints (:func:`endpoint_problem`, then Zenoh's own
parser) and key prefix when the config is read; on this machine (``check-config``, ``run``),
its Zenoh file and what the TLS settings in it need (:func:`host_problems`)."""

from __future__ import annotations

import ipaddress
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from uwbd.config.checks import Report
from uwbd.config.model import Config
from uwbd.config.ros2 import EXTRA_HINT, EXTRA_MODULES, missing_extra
from uwbd.config.schema import HOST_PORT_PROTOCOLS, HOSTNAME, ZENOH_PROTOCOLS
from uwbd.config.spelling import known, show
from uwbd.config.zenoh_tls import Identity, check_material


def check_zenoh(r: Report, zenoh: Mapping[str, Any]) -> None:
    good: dict[str, list[tuple[int, str]]] = {}
    for key in ("connect", "listen"):
        good[key] = []
        seen: set[str] = set()
        for k, endpoint in enumerate(zenoh.get(key, [])):
            problem = endpoint_problem(endpoint)
            if problem is not None:
                r.error(f"zenoh.{key}[{k}]", f"{show(endpoint)}: {problem}")
                continue
            if endpoint in seen:
                r.warn(f"zenoh.{key}[{k}]", f"{show(endpoint)} is listed twice")
            seen.add(endpoint)
            good[key].append((k, endpoint))
    if "config" not in zenoh:  # (a Zenoh file may hold authentication or access control)
        for k, endpoint in good["listen"]:
            if plaintext_beyond_this_host(endpoint):
                r.warn(f"zenoh.listen[{k}]", f"{show(endpoint)} is reachable from the network "
                       "without encryption or authentication: anyone there can read the "
                       "poses and publish false ones; listen on 127.0.0.1 (a router reaches "
                       "it), or secure it (docs/security.md)")
        if zenoh.get("multicast_scouting"):
            r.warn("zenoh.multicast_scouting", "true announces this robot to the whole LAN and "
                   "meshes with any peer that answers, without encryption or authentication: "
                   "anyone there can read the poses and publish false ones; leave it false "
                   "(this host only, or connect to a router), or secure it "
                   "(docs/security.md)")
    if zenoh.get("mode") == "client" and not zenoh.get("connect"):
        r.error("zenoh.mode", "\"client\" needs a zenoh.connect endpoint (a router or peer)")
    prefix = zenoh.get("prefix", "").strip("/")
    if prefix and any(c in prefix for c in "*$?#"):
        r.error("zenoh.prefix", f"{show(zenoh['prefix'])}: no wildcards (*, $*) nor # or ? in "
                "a key to publish on")
        prefix = ""
    if good["connect"] or good["listen"] or prefix:
        _check_with_zenoh(r, zenoh, good, prefix)


def _check_with_zenoh(r: Report, zenoh_table: Mapping[str, Any],
                      endpoints: Mapping[str, list[tuple[int, str]]], prefix: str) -> None:
    """Zenoh's own parser as a second opinion on the endpoints and the key prefix."""
    import zenoh  # noqa: PLC0415 - only for configs that key endpoints

    def said(err: zenoh.ZError) -> str:  # without the Rust source location
        return re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(err))

    for key, listed in endpoints.items():
        for k, endpoint in listed:
            try:
                zenoh.Config.from_json5(json.dumps({key: {"endpoints": [endpoint]}}))
            except zenoh.ZError as err:
                r.error(f"zenoh.{key}[{k}]", f"{show(endpoint)}: Zenoh: {said(err)}")
    if prefix:
        try:
            zenoh.KeyExpr(f"{prefix}/pose")
        except zenoh.ZError as err:
            r.error("zenoh.prefix", f"{show(zenoh_table['prefix'])}: Zenoh: {said(err)}")


def endpoint_problem(endpoint: str) -> str | None:
    """What is wrong with a Zenoh endpoint ``<protocol>/<address>[?<metadata>][#<config>]``,
    or ``None``."""
    locator = endpoint.partition("#")[0].partition("?")[0]
    protocol, slash, address = locator.partition("/")
    if not slash or not protocol:
        return "expected <protocol>/<address>, e.g. tcp/192.168.1.10:7447"
    if protocol not in ZENOH_PROTOCOLS:
        return f"unknown protocol {show(protocol)}" + known(protocol, ZENOH_PROTOCOLS)
    if not address:
        return f"no address after {protocol}/"
    if protocol in HOST_PORT_PROTOCOLS:
        return _host_port_problem(address)
    if protocol == "unixsock-stream" and not address.startswith("/"):
        return "expected an absolute socket path (unixsock-stream//run/uwbd/zenoh.sock)"
    return None


def plaintext_beyond_this_host(endpoint: str) -> bool:
    """A tcp/udp/ws endpoint whose host is not a loopback address: anyone on the network
    reaches it, unencrypted and unauthenticated."""
    protocol, _, address = endpoint.partition("#")[0].partition("?")[0].partition("/")
    if protocol not in ("tcp", "udp", "ws"):
        return False
    host = address[1:].partition("]")[0] if address.startswith("[") else address.rpartition(":")[0]
    if host == "localhost":
        return False
    try:
        return not ipaddress.ip_address(host).is_loopback
    except ValueError:
        return True  # a host name, or a wildcard: whichever interface it names


def _host_port_problem(address: str) -> str | None:
    if address.startswith("["):
        host, bracket, rest = address[1:].partition("]")
        if not bracket or not rest.startswith(":"):
            return "expected [IPv6 address]:port, e.g. [::1]:7447"
        port = rest[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return f"{show(host)} is not an IPv6 address"
    else:
        if address.count(":") > 1:
            return "an IPv6 address goes in brackets: [::1]:7447"
        host, colon, port = address.rpartition(":")
        if not colon or not host:
            return "expected host:port, e.g. 192.168.1.10:7447"
        if re.fullmatch(r"[\d.]+", host):
            try:
                ipaddress.IPv4Address(host)
            except ValueError:
                return f"{show(host)} is not an IPv4 address"
        elif not HOSTNAME.fullmatch(host):
            return f"{show(host)} is not a host name"
    if not port.isascii() or not port.isdigit() or int(port) > 65535:
        return f"port {show(port)}: expected 0..65535"
    return None


SECURE_PROTOCOLS = ("tls", "quic")
TLS = "transport/link/tls/"


def check_zenoh_file(r: Report, zcfg: Mapping[str, Any]) -> list[Identity]:
    """``zenoh.config`` on this machine (``check-config`` and ``run``; a replay on another
    machine needs none of it): the file is there and Zenoh reads it merged with the table's
    keys; a ``tls/`` or ``quic/`` endpoint has the key, certificates and CA it needs, every
    file the TLS settings name exists and holds what it should (:mod:`.zenoh_tls`). Returns
    the certificates' identities that passed."""
    import zenoh  # noqa: PLC0415 - only for configs that name a Zenoh file

    from uwbd.config import zenoh_session as zs  # noqa: PLC0415

    path = zcfg.get("config")
    if path is None:
        return []
    if not Path(path).is_file():
        r.error("zenoh.config", f"{path}: no such file (a Zenoh config file, JSON5)")
        return []
    try:
        merged = zs.session_config(dict(zcfg))
    except zenoh.ZError as err:
        r.error("zenoh.config", f"{path}: Zenoh: {zs.zenoh_reason(err)}")
        return []

    def get(key: str) -> Any:
        try:
            return json.loads(merged.get_json(key))
        except (zenoh.ZError, ValueError):
            return None

    def given(name: str) -> bool:
        return bool(get(TLS + name) or get(TLS + name + "_base64"))

    # a TLS client without a CA of its own trusts the Web PKI's (Zenoh's default): a router
    # with a public certificate needs no file; with mTLS each side shows its own
    mtls = bool(get(TLS + "enable_mtls"))
    needs = {"listen": ["listen_private_key", "listen_certificate"]
             + (["root_ca_certificate"] if mtls else []),
             "connect": ["root_ca_certificate", "connect_private_key", "connect_certificate"]
             if mtls else []}
    for section, names in needs.items():
        secure = [e for e in zs.endpoints(merged, section)
                  if e.partition("/")[0] in SECURE_PROTOCOLS]
        missing = [n for n in names if not given(n)]
        if secure and missing:
            r.error("zenoh.config", f"{path}: {section} endpoint {secure[0]} needs "
                    + ", ".join(f"transport.link.tls.{n}" for n in missing)
                    + (" (enable_mtls: each side shows a certificate)" if mtls else ""))
    for name in ("root_ca_certificate", "listen_private_key", "listen_certificate",
                 "connect_private_key", "connect_certificate"):
        file = get(TLS + name)
        if isinstance(file, str) and not Path(file).is_file():
            r.error("zenoh.config", f"{path}: transport.link.tls.{name} {file}: no such file")
    return check_material(lambda name: get(TLS + name),
                          lambda what: r.error("zenoh.config", f"{path}: {what}"))


def host_problems(config: Config, where: str) -> Report:
    """What this machine lacks to run ``config`` (its Zenoh file and what that names), one
    line each, and the ``ros2`` extra when ``[ros2]`` is on; nothing where Zenoh is off. Its
    warnings: a certificate whose name the key prefix does not follow."""
    r = Report(where)
    zcfg = config.zenoh
    missing = missing_extra() if config.ros2_settings.enabled else None
    if missing is not None:
        r.error("ros2.enabled", f"the ROS 2 topics need the ros2 extra ({missing}, for "
                f"{EXTRA_MODULES[missing]}, is missing): {EXTRA_HINT}")
    if not zcfg.get("enabled", True):
        return r
    if "config" not in zcfg:  # (a TLS client needs nothing: it trusts the Web PKI's CAs)
        for k, endpoint in enumerate(zcfg.get("listen", [])):
            if str(endpoint).partition("/")[0] in SECURE_PROTOCOLS:
                r.error(f"zenoh.listen[{k}]", f"{show(endpoint)}: listening on TLS needs a "
                        "key and certificate: name a Zenoh config file that gives them with "
                        "zenoh.config (docs/security.md)")
    for identity in check_zenoh_file(r, zcfg):
        own = f"uwbd/{identity.common_name}"
        if identity.side == "connect" and identity.common_name and config.zenoh_prefix != own:
            r.warn("zenoh.config", f"{identity.certificate} is {identity.common_name}'s "
                   f"certificate, and this daemon publishes on {config.zenoh_prefix}/**: a "
                   f"router's access control as shipped (config/zenoh/router.json5) admits "
                   f"{identity.common_name}'s puts on {own}/** only and drops these; set "
                   f'[robot] name = "{identity.common_name}" (or zenoh.prefix = "{own}")')
    return r
