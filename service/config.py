"""The service configuration: one TOML file, environment overrides, validated at start.

Every key is declared by a typed dataclass field below, so an unknown key, a wrong type or an
out-of-range value is refused with an error naming the key (``dicom.port: ...``) before the
service opens a socket. Any scalar key can be overridden from the environment as
``SLAMTKA_<SECTION>_<KEY>`` in capitals, e.g. ``SLAMTKA_DICOM_PORT=11113`` or
``SLAMTKA_DICOM_TLS_ENABLED=true``; destinations and ``dicom.callers`` are configured in the
file only.
``deploy/slamtka.example.toml`` documents every key.
"""

from __future__ import annotations

import copy
import dataclasses
import ipaddress
import os
import re
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slamtka.drivers.config_tables import ConfigError, build_table

__all__ = ["ConfigError", "ServiceConfig", "DicomConfig", "TlsConfig", "Destination",
           "CallerBinding", "load_config", "config_from_dict", "validate_ae_title",
           "normalise_fingerprint", "ENV_PREFIX"]

ENV_PREFIX = "SLAMTKA_"
_AE_TITLE = re.compile(r"^[\x20-\x5b\x5d-\x7e]{1,16}$")  # DICOM AE VR: no backslash, no control
_OBJECT_KINDS = ("sr", "sc")  # the DICOM results a destination can be sent (OutgoingObject.kind)


def validate_ae_title(value: str, where: str) -> str:
    if not _AE_TITLE.match(value) or not value.strip():
        raise ConfigError(f"{where}: {value!r} is not a valid AE title (1-16 printable "
                          "characters, no backslash)")
    return value.strip()


def normalise_fingerprint(text: str) -> str:
    """A SHA-256 certificate fingerprint as lower-case hex (``openssl x509 -fingerprint
    -sha256`` prints it in capitals with colons; both are accepted in the file)."""
    return text.replace(":", "").strip().lower()


def _check_fingerprint(where: str, text: str) -> None:
    if text and not re.fullmatch(r"[0-9a-f]{64}", normalise_fingerprint(text)):
        raise ConfigError(f"{where}: {text!r} is not a SHA-256 fingerprint (64 hex digits, "
                          "colons allowed)")


def _check_networks(where: str, addresses: list[str]) -> None:
    for i, address in enumerate(addresses):
        try:
            ipaddress.ip_network(address, strict=False)
        except ValueError:
            raise ConfigError(f"{where}[{i}]: {address!r} is not an IP address or network "
                              "(e.g. 10.0.3.0/24)") from None


def _check_range(where: str, value: float, low: float, high: float) -> None:
    if not low <= value <= high:
        raise ConfigError(f"{where}: {value} is outside [{low}, {high}]")


@dataclass(frozen=True)
class TlsConfig:
    """Mutual TLS on the DICOM port: our certificate and key, the CAs clients must chain to."""

    enabled: bool = False
    certificate: Path | None = None
    private_key: Path | None = None
    ca_certificates: Path | None = None
    min_version: str = "1.2"

    def check(self, where: str) -> None:
        if self.min_version not in ("1.2", "1.3"):
            raise ConfigError(f"{where}.min_version: {self.min_version!r} must be '1.2' or '1.3'")
        if self.enabled:
            for name in ("certificate", "private_key", "ca_certificates"):
                if getattr(self, name) is None:
                    raise ConfigError(f"{where}.{name}: required when TLS is enabled")


@dataclass(frozen=True)
class CallerBinding:
    """A calling AE title bound to where it may call from (and, with TLS, its certificate).

    Another address using the title, or the certificate, is refused; a bound caller also
    has one association slot that unbound callers cannot take.
    """

    ae_title: str = ""
    addresses: list[str] = field(default_factory=list)  # IPs or networks
    certificate_sha256: str = ""  # the client certificate it must present ("" = any valid)

    def check(self, where: str) -> None:
        validate_ae_title(self.ae_title, f"{where}.ae_title")
        if not self.addresses:
            raise ConfigError(f"{where}.addresses: list the addresses {self.ae_title} calls from")
        _check_networks(f"{where}.addresses", self.addresses)
        _check_fingerprint(f"{where}.certificate_sha256", self.certificate_sha256)


@dataclass(frozen=True)
class DicomConfig:
    """The receiving side (SCP) and the identity used when sending results."""

    ae_title: str = "SLAMTKA"
    bind_address: str = "127.0.0.1"
    port: int = 11112
    allowed_calling_ae_titles: list[str] = field(default_factory=list)
    allowed_source_addresses: list[str] = field(default_factory=list)  # IPs/networks; [] = any
    health_ae_title: str = "SLAMTKA_HEALTH"  # may associate and C-ECHO, never store
    max_pdu_bytes: int = 262144
    max_message_bytes: int = 32 * 1024 * 1024  # one received dataset, assembled in memory
    # Instances decoded and spooled at once (each holds a few copies of its frame); a store
    # beyond waits up to memory_wait_s, then is refused with 0xA700 (the C-arm retries).
    max_frames_in_memory: int = 2
    memory_wait_s: float = 5.0
    max_associations: int = 4
    max_associations_per_address: int = 2  # storing associations one source address may hold
    callers: list[CallerBinding] = field(default_factory=list)
    max_connections: int = 512  # open sockets, before and during associations
    max_connections_per_peer: int = 8  # per source address
    request_timeout_s: float = 5.0  # TLS handshake, then the first PDU, each within this
    idle_timeout_s: float = 30.0
    dimse_timeout_s: float = 30.0
    tls: TlsConfig = field(default_factory=TlsConfig)

    def check(self, where: str) -> None:
        validate_ae_title(self.ae_title, f"{where}.ae_title")
        if not self.allowed_calling_ae_titles:
            raise ConfigError(f"{where}.allowed_calling_ae_titles: list the C-arms allowed to "
                              "send (an empty list would refuse every association)")
        for i, title in enumerate(self.allowed_calling_ae_titles):
            validate_ae_title(title, f"{where}.allowed_calling_ae_titles[{i}]")
        validate_ae_title(self.health_ae_title, f"{where}.health_ae_title")
        if self.health_ae_title in self.allowed_calling_ae_titles:
            raise ConfigError(f"{where}.health_ae_title: must differ from the sending C-arms' "
                              "AE titles (it may not store)")
        try:
            ipaddress.ip_address(self.bind_address)
        except ValueError:
            raise ConfigError(f"{where}.bind_address: {self.bind_address!r} is not an IP address "
                              "(e.g. 0.0.0.0 for all interfaces)") from None
        _check_range(f"{where}.port", self.port, 0, 65535)  # 0: any free port (tests)
        _check_range(f"{where}.max_pdu_bytes", self.max_pdu_bytes, 4096, 16 * 1024 * 1024)
        _check_range(f"{where}.max_message_bytes", self.max_message_bytes, 1024 * 1024, 1 << 30)
        _check_range(f"{where}.max_frames_in_memory", self.max_frames_in_memory, 1, 64)
        _check_range(f"{where}.memory_wait_s", self.memory_wait_s, 0.0, 60.0)
        _check_range(f"{where}.max_associations", self.max_associations, 1, 64)
        _check_range(f"{where}.max_associations_per_address", self.max_associations_per_address,
                     1, 64)
        for i, caller in enumerate(self.callers):
            caller.check(f"{where}.callers[{i}]")
            if caller.ae_title not in self.allowed_calling_ae_titles:
                raise ConfigError(f"{where}.callers[{i}].ae_title: {caller.ae_title!r} is not in "
                                  "allowed_calling_ae_titles")
        titles = [c.ae_title for c in self.callers]
        if len(set(titles)) != len(titles):
            raise ConfigError(f"{where}.callers: each AE title may be bound once, got {titles}")
        if any(c.certificate_sha256 for c in self.callers) and not self.tls.enabled:
            raise ConfigError(f"{where}.callers: a certificate_sha256 needs tls.enabled = true")
        if self.callers and self.max_associations < 2:
            raise ConfigError(f"{where}.max_associations: at least 2 when callers are bound "
                              "(one slot is kept for them)")
        _check_range(f"{where}.max_connections", self.max_connections, self.max_associations,
                     4096)
        _check_range(f"{where}.max_connections_per_peer", self.max_connections_per_peer, 1,
                     self.max_connections)
        _check_range(f"{where}.request_timeout_s", self.request_timeout_s, 0.1, 600.0)
        _check_networks(f"{where}.allowed_source_addresses", self.allowed_source_addresses)
        _check_range(f"{where}.idle_timeout_s", self.idle_timeout_s, 1.0, 3600.0)
        _check_range(f"{where}.dimse_timeout_s", self.dimse_timeout_s, 1.0, 3600.0)
        self.tls.check(f"{where}.tls")


@dataclass(frozen=True)
class Destination:
    """A DICOM node that receives the results (OR display, PACS)."""

    name: str = ""
    ae_title: str = ""
    host: str = ""
    port: int = 104
    objects: list[str] = field(default_factory=lambda: list(_OBJECT_KINDS))
    tls: bool = False
    ca_certificates: Path | None = None
    certificate: Path | None = None
    private_key: Path | None = None
    server_name: str = ""  # the name its certificate must carry; default: host
    certificate_sha256: str = ""  # pin: the SHA-256 of its certificate ("" = any that names it)

    def check(self, where: str) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", self.name):
            raise ConfigError(f"{where}.name: {self.name!r} must be 1-40 letters, digits, _ . -")
        validate_ae_title(self.ae_title, f"{where}.ae_title")
        if not self.host:
            raise ConfigError(f"{where}.host: required")
        _check_range(f"{where}.port", self.port, 1, 65535)
        bad = sorted(set(self.objects) - set(_OBJECT_KINDS))
        if bad or not self.objects:
            raise ConfigError(f"{where}.objects: {self.objects} must be a non-empty subset of "
                              f"{list(_OBJECT_KINDS)}")
        if self.tls and self.ca_certificates is None:
            raise ConfigError(f"{where}.ca_certificates: required when tls = true")
        _check_fingerprint(f"{where}.certificate_sha256", self.certificate_sha256)


@dataclass(frozen=True)
class CarmConfig:
    """The C-arm: its calibration, its encoder link, its kinematics and the patient set-up.

    ``link``, ``kinematics`` and ``setup`` are passed to the drivers' ``LinkConfig``,
    ``CArmKinematics`` and ``PatientSetup`` (absent keys take their defaults) and checked
    by them at start.
    """

    calibration: Path | None = None  # the default: C-arms without their own (service.calibrations)
    calibration_match: str = "device_serial_number"  # or station_name, calling_ae_title
    encoder_port: str = ""  # serial device; empty: no link, DICOM positioner angles only
    max_reading_age_s: float = 0.1
    angle_check_deg: float = 3.0  # encoder vs DICOM positioner beam direction
    # How far (s) the C-arm's frame times may be off the encoder stream and still be
    # corrected (service.clock); beyond, a view falls back to its positioner angles.
    max_clock_offset_s: float = 2.0
    link: dict = field(default_factory=dict)
    kinematics: dict = field(default_factory=dict)
    setup: dict = field(default_factory=dict)

    def check(self, where: str, drivers: bool = True) -> None:
        """Without ``drivers`` the link, kinematics and set-up are not parsed: the drivers
        import numpy and pyserial (0.13 s), which a health check need not pay."""
        if self.calibration_match not in ("device_serial_number", "station_name", "calling_ae_title"):
            raise ConfigError(f"{where}.calibration_match: {self.calibration_match!r} must be "
                              "'device_serial_number', 'station_name' or 'calling_ae_title'")
        _check_range(f"{where}.angle_check_deg", self.angle_check_deg, 0.1, 45.0)
        _check_range(f"{where}.max_clock_offset_s", self.max_clock_offset_s, 0.0, 60.0)
        if not drivers:
            return
        from slamtka.drivers.encoder_link import LinkConfig
        from slamtka.drivers.kinematics import CArmKinematics, PatientSetup
        from slamtka.solver.anatomy import Landmarks

        for key, parse in (("link", LinkConfig.from_config),
                           ("kinematics", CArmKinematics.from_config)):
            try:
                parse(getattr(self, key))
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{where}.{key}: {exc}") from None
        try:
            setup = PatientSetup.from_config(Landmarks.nominal(), self.setup)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}.setup: {exc}") from None
        if setup.reference_view > 1:  # a case is measured as soon as it has two views
            raise ConfigError(f"{where}.setup: reference_view {setup.reference_view} must be 0 or 1 "
                              "(a run may have only two views)")
        link = LinkConfig.from_config(self.link)
        _check_range(f"{where}.max_reading_age_s", self.max_reading_age_s, 0.001, link.max_age_s)


@dataclass(frozen=True)
class PipelineConfig:
    """Case assembly and the measurement pipeline."""

    min_view_separation_deg: float = 15.0
    max_views: int = 6
    manual_contours_dir: Path | None = None  # contour documents drawn by hand, by SOP UID
    # A view of a new DICOM series starts a new pin set (for C-arms that open a series per
    # pin placement); off by default: the pins themselves are compared.
    new_set_on_new_series: bool = False

    def check(self, where: str) -> None:
        _check_range(f"{where}.min_view_separation_deg", self.min_view_separation_deg, 1.0, 90.0)
        _check_range(f"{where}.max_views", self.max_views, 2, 16)


@dataclass(frozen=True)
class SenderConfig:
    """The durable retry queue of outgoing C-STOREs."""

    retry_initial_s: float = 2.0
    retry_max_s: float = 300.0
    max_attempts: int = 50
    timeout_s: float = 30.0

    def check(self, where: str) -> None:
        _check_range(f"{where}.retry_initial_s", self.retry_initial_s, 0.01, 3600.0)
        _check_range(f"{where}.retry_max_s", self.retry_max_s, self.retry_initial_s, 86400.0)
        _check_range(f"{where}.max_attempts", self.max_attempts, 1, 100000)
        _check_range(f"{where}.timeout_s", self.timeout_s, 1.0, 600.0)


@dataclass(frozen=True)
class HealthConfig:
    """How the service reports its health: the status snapshot and the HTTP endpoint
    (Prometheus ``/metrics`` and ``/healthz``), on the loopback interface unless told."""

    snapshot_interval_s: float = 2.0  # status.json is stale after three intervals
    http_enabled: bool = True
    http_bind_address: str = "127.0.0.1"
    http_port: int = 9112
    # A run is bounded (the global set-up search included); a worker busier than this is stuck.
    max_run_s: float = 120.0

    def check(self, where: str) -> None:
        _check_range(f"{where}.snapshot_interval_s", self.snapshot_interval_s, 0.2, 60.0)
        _check_range(f"{where}.http_port", self.http_port, 0, 65535)
        _check_range(f"{where}.max_run_s", self.max_run_s, 5.0, 3600.0)
        try:
            ipaddress.ip_address(self.http_bind_address)
        except ValueError:
            raise ConfigError(f"{where}.http_bind_address: {self.http_bind_address!r} is not an "
                              "IP address") from None


@dataclass(frozen=True)
class RetentionConfig:
    """How long what the service keeps is kept (service.retention)."""

    archive_after_hours: float = 12.0  # a case idle this long, all delivered, leaves the live spool
    keep_days: float = 30.0  # then its frames and results are deleted (audit log kept)
    min_free_mb: float = 2048.0  # below this much free disk no new frame is received
    interval_s: float = 600.0  # how often the service archives and prunes

    def check(self, where: str) -> None:
        _check_range(f"{where}.archive_after_hours", self.archive_after_hours, 0.0, 24.0 * 365)
        _check_range(f"{where}.keep_days", self.keep_days, 0.0, 3650.0)
        _check_range(f"{where}.min_free_mb", self.min_free_mb, 0.0, 1e9)
        _check_range(f"{where}.interval_s", self.interval_s, 1.0, 86400.0)


@dataclass(frozen=True)
class ServiceConfig:
    """The whole configuration; relative paths are relative to the TOML file."""

    data_dir: Path = Path("/var/lib/slamtka")
    plans_dir: Path | None = None  # default: data_dir/plans
    output_dir: Path | None = None  # default: data_dir/output
    institution: str = ""
    dicom: DicomConfig = field(default_factory=DicomConfig)
    carm: CarmConfig = field(default_factory=CarmConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    sender: SenderConfig = field(default_factory=SenderConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    retention: RetentionConfig = field(default_factory=RetentionConfig)
    destinations: list[Destination] = field(default_factory=list)
    source: Path | None = None  # the TOML file this came from (not a key)

    def check(self, drivers: bool = True) -> None:
        """Every section's values; ``drivers``: see :meth:`CarmConfig.check`."""
        self.dicom.check("dicom")
        self.carm.check("carm", drivers)
        self.pipeline.check("pipeline")
        self.sender.check("sender")
        self.health.check("health")
        self.retention.check("retention")
        names = [d.name for d in self.destinations]
        if len(set(names)) != len(names):
            raise ConfigError(f"destinations: names must be unique, got {names}")
        for i, dest in enumerate(self.destinations):
            dest.check(f"destinations[{i}]")

    # Folders under data_dir (fixed names: an operator finds everything in one place).
    @property
    def spool_dir(self) -> Path:
        return self.data_dir / "spool"

    @property
    def queue_dir(self) -> Path:
        return self.data_dir / "queue"

    @property
    def audit_log(self) -> Path:
        return self.data_dir / "audit.jsonl"

    @property
    def status_file(self) -> Path:
        return self.data_dir / "status.json"

    @property
    def plans(self) -> Path:
        return self.plans_dir or self.data_dir / "plans"

    @property
    def output(self) -> Path:
        return self.output_dir or self.data_dir / "output"


# -- generic typed construction --------------------------------------------------------------

def _parse_env_value(text: str, hint: Any, where: str) -> Any:
    """An environment string as the TOML value it stands for."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        hint = [a for a in typing.get_args(hint) if a is not type(None)][0]
    if hint is bool:
        if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise ConfigError(f"{where}: expected true or false, got {text!r}")
        return text.lower() in ("true", "1", "yes")
    try:
        if hint is int:
            return int(text)
        if hint is float:
            return float(text)
    except ValueError:
        raise ConfigError(f"{where}: {text!r} is not a number") from None
    if typing.get_origin(hint) is list:
        return [part.strip() for part in text.split(",") if part.strip()]
    return text


def _env_keys(cls: type, path: tuple[str, ...] = ()) -> dict[str, tuple[tuple[str, ...], Any]]:
    """``SLAMTKA_...`` variable name -> (key path, type) for every overridable key."""
    out = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if f.name == "source" or typing.get_origin(hint) is list and dataclasses.is_dataclass(
                typing.get_args(hint)[0]):
            continue  # tables of tables (destinations, dicom.callers) live in the file only
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            out.update(_env_keys(hint, path + (f.name,)))
        elif hint is not dict:
            key = path + (f.name,)
            out[ENV_PREFIX + "_".join(key).upper()] = (key, hint)
    return out


def _apply_env(table: dict, environ: Mapping[str, str]) -> dict:
    known = _env_keys(ServiceConfig)
    sections = {f"{ENV_PREFIX}{name.upper()}_"
                for name, hint in typing.get_type_hints(ServiceConfig).items()
                if dataclasses.is_dataclass(hint)}
    for name, text in environ.items():
        if name not in known:
            # A misspelt key of a known section is an error; other SLAMTKA_ names are not ours.
            if any(name.startswith(prefix) for prefix in sections):
                raise ConfigError(f"environment variable {name}: not a configuration key")
            continue
        path, hint = known[name]
        node = table
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{'.'.join(path)}: expected a table in the file")
        node[path[-1]] = _parse_env_value(text, hint, f"{name} ({'.'.join(path)})")
    return table


def config_from_dict(table: dict, base: Path | None = None,
                     environ: Mapping[str, str] | None = None, drivers: bool = True) -> ServiceConfig:
    """A validated configuration from a parsed TOML table (and the environment);
    ``drivers``: see :meth:`CarmConfig.check`."""
    table = _apply_env(copy.deepcopy(table), os.environ if environ is None else environ)
    config = build_table(ServiceConfig, table, "", base)
    config.check(drivers)
    return config


def load_config(path: Path, environ: Mapping[str, str] | None = None,
                drivers: bool = True) -> ServiceConfig:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: configuration file not found")
    try:
        table = tomllib.loads(path.read_text())
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text (UTF-8) file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    config = config_from_dict(table, path.parent.resolve(), environ, drivers)
    return dataclasses.replace(config, source=path.resolve())
