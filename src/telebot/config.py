"""Settings, validated by pydantic: TOML files and flags become these models.

Every model forbids unknown keys, so a misspelt key is an error naming the key and the
file, never a silent default. :func:`load_toml` turns any problem into one
:class:`~telebot.errors.ConfigError` line.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any, Literal, Self, TypeVar

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

from telebot.errors import ConfigError

__all__ = [
    "DIAL_LEASE",
    "HARD_MAX_ANGULAR_SPEED",
    "HARD_MAX_LINEAR_SPEED",
    "SAFE_OBSERVER_TOPICS",
    "AppConfig",
    "CallSettings",
    "CipherChoice",
    "DriveSettings",
    "FollowSettings",
    "MemorySettings",
    "PeopleSettings",
    "ReconnectSettings",
    "RecordedStream",
    "RecordingSettings",
    "RelaySettings",
    "RobotConfig",
    "RobotSettings",
    "Ros2Settings",
    "SafetySettings",
    "ScreenSettings",
    "ServiceSettings",
    "SimSettings",
    "StrictModel",
    "TransportSettings",
    "VideoConfig",
    "WalkerSettings",
    "ZenohSettings",
    "ZenohTlsSettings",
    "default_home",
    "format_validation_error",
    "load_toml",
]


class StrictModel(BaseModel):
    """Base of every settings model: unknown keys are errors, values are checked on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


class ZenohTlsSettings(StrictModel):
    """Mutual TLS to a telebot router (``telebot-router cert`` makes the three files).

    Set all three or none; each must name an existing file (relative paths are taken
    from the current directory). With them, ``tls/...`` endpoints prove this client's
    certificate to the router and check the router's against ``ca``.
    """

    #: The router's CA certificate (PEM): the router must present a certificate it signed.
    ca: Path | None = None
    #: This client's certificate (PEM), issued by the router's CA.
    cert: Path | None = None
    #: This client's private key (PEM).
    key: Path | None = None

    @property
    def enabled(self) -> bool:
        """Whether any TLS file is set."""
        return any(p is not None for p in (self.ca, self.cert, self.key))


#: The link lease (s) a zenoh session that dials announces by default (``[transport.zenoh]
#: lease``; at least twice ``[call] timeout``).
DIAL_LEASE = 1.0


class ZenohSettings(StrictModel):
    """How the zenoh transport connects. The defaults need no router and no config file."""

    mode: Literal["peer", "client"] = "peer"
    #: Endpoints to listen on, e.g. ``["tcp/127.0.0.1:7447"]``; empty = zenoh's default.
    listen: list[str] = Field(default_factory=list)
    #: Endpoints (peers or routers) to connect to, e.g. ``["tcp/10.0.0.5:7447"]``.
    connect: list[str] = Field(default_factory=list)
    #: Find peers on the local network by UDP multicast (zenoh's default in peer mode).
    multicast_scouting: bool = True
    #: A zenoh JSON5 config file loaded first (TLS, ACL, ...); the keys above override it.
    config_file: Path | None = None
    #: Extra zenoh config, path -> value, inserted last, e.g.
    #: ``{"transport/link/tls/root_ca_certificate" = "/etc/telebot/ca.pem"}``.
    options: dict[str, Any] = Field(default_factory=dict)
    #: Bound on how long closing the session may take, in seconds.
    close_timeout: float = Field(default=2.0, gt=0, le=60)
    #: Samples buffered between zenoh's threads and the event loop; the oldest drop beyond.
    queue_size: int = Field(default=4096, ge=16, le=1_000_000)
    #: ...and at most this many bytes per subscription (8 MB: 256 full 32 KB frames), so a
    #: flood costs bounded memory whatever its frame size.
    queue_bytes: int = Field(default=8 << 20, ge=64 << 10, le=1 << 30)
    #: Client certificate, key and CA for ``tls/`` endpoints (telebot-router).
    tls: ZenohTlsSettings = Field(default_factory=ZenohTlsSettings)
    #: The link lease this session announces (s): the other end drops the link after this
    #: long without a word from it. Unset: :data:`DIAL_LEASE` (1 s; at least twice ``[call]
    #: timeout``) for a session that dials (:attr:`dials`), zenoh's own (10 s) for one that
    #: listens, so that after an outage the listener has dropped the link and the dialler,
    #: answered with a reset, dials afresh at once (a zenoh config file or a
    #: ``transport/link/tx/lease`` option rules instead).
    lease: float | None = Field(default=None, ge=0.1, le=3600)
    #: A second zenoh session, dialling the same ``connect`` endpoints, for calls' data keys
    #: (``.../data``: video, pose, sound) and the first for everything else (stops,
    #: heartbeats, the handshake, presence): a connection of their own, so pictures never
    #: fill the congestion window that stops and heartbeats need (protocol §2.3). Unset: on
    #: for a session that dials (:attr:`dials`) a ``quic/`` endpoint.
    data_session: bool | None = None
    # The call timeout of the AppConfig this belongs to (AppConfig.fit_lease), 0 if none.
    _call_timeout: float = PrivateAttr(default=0.0)

    @property
    def dials(self) -> bool:
        """Whether this session dials: client mode, or ``connect`` endpoints and no ``listen``."""
        return self.mode == "client" or (bool(self.connect) and not self.listen)

    @property
    def splits_data(self) -> bool:
        """Whether this transport opens :attr:`data_session`'s second session."""
        if self.data_session is not None:
            return self.data_session
        return self.dials and any(e.startswith("quic/") for e in self.connect)

    @property
    def dial_lease(self) -> float:
        """The lease (s) a dialling session announces when ``lease`` is unset:
        :data:`DIAL_LEASE`, at least twice its config's ``[call] timeout``."""
        return max(DIAL_LEASE, 2 * self._call_timeout)


class MemorySettings(StrictModel):
    """The in-process transport: which hub to join and under which node name."""

    hub: str = "default"
    #: Node name on the hub (links are set between node names); default: a unique name.
    node: str | None = None


class TransportSettings(StrictModel):
    """Which transport to use (``kind``) and the settings of each built-in one."""

    kind: str = "zenoh"
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    memory: MemorySettings = Field(default_factory=MemorySettings)
    #: Settings for a third-party transport, passed through as they are.
    options: dict[str, Any] = Field(default_factory=dict)


#: ``[call] cipher``: the cipher suites an end accepts (see ``telebot.channels.suites``).
CipherChoice = Literal["auto", "aesgcm", "chachapoly"]


class CallSettings(StrictModel):
    """Timing of calls: heartbeats, drop detection and set-up; the cipher suite."""

    #: Heartbeats sent per second on the control lane (20 Hz by default).
    heartbeat_hz: float = Field(default=20.0, gt=0, le=1000)
    #: A call drops when no valid frame arrived from the peer for this long (seconds).
    timeout: float = Field(default=0.5, gt=0, le=60)
    #: How long a caller waits for the robot to answer (seconds).
    connect_timeout: float = Field(default=5.0, gt=0, le=600)
    #: Cipher suite: "auto" accepts both, AES-256-GCM preferred when this CPU has AES
    #: instructions (ChaCha20-Poly1305 otherwise); "aesgcm" or "chachapoly" accepts only
    #: that one (a peer that accepts only the other cannot call or be called).
    cipher: CipherChoice = "auto"


class ReconnectSettings(StrictModel):
    """What a user client does when its call drops (``telebot.connect``, ``chat``, ``ui``).

    It calls the robot again, waiting ``base`` seconds before the first attempt and
    doubling the wait after each failed one up to ``cap`` (each wait is shortened by a
    random share of up to a half, so many clients do not call back in step). Each attempt
    keeps calling for ``call.connect_timeout`` seconds. A refusal (no longer a contact)
    or ``give_up_after`` seconds without a call end it. The robot stays stopped whatever
    happens: its driver re-arms it.
    """

    #: Call the robot again after a drop (a hang-up is never redialled).
    enabled: bool = True
    #: Seconds before the first attempt; the wait doubles after each failed attempt ...
    base: float = Field(default=0.1, gt=0, le=60)
    #: ... up to this many seconds.
    cap: float = Field(default=2.0, gt=0, le=600)
    #: Stop trying after this many seconds without a call (0: never).
    give_up_after: float = Field(default=300.0, ge=0)


class FleetSettings(StrictModel):
    """The fleet page (``telebot-user ui`` without a robot name).

    Presence shows only a robot's name and key; its battery, state, driver and link come
    from a call. ``watch``: call every trusted robot online to show them (False: list names
    only, and call a robot when it is opened).
    """

    #: Call each trusted robot online to show its battery, state, driver and link.
    watch: bool = True
    #: Robots the page calls at most.
    max_calls: int = Field(default=32, ge=1, le=1000)
    #: A robot that has not acknowledged STOP ALL within this many seconds is reported.
    stop_timeout: float = Field(default=2.0, gt=0, le=30)


#: No configuration may make the simulated base faster than this (m/s).
HARD_MAX_LINEAR_SPEED = 1.5
#: No configuration may make the simulated base turn faster than this (rad/s).
HARD_MAX_ANGULAR_SPEED = 3.0


class WalkerSettings(StrictModel):
    """One ``[[sim.walkers]]`` entry: a simulated person walking a scripted path.

    Each starts when the robot does; see :class:`telebot.robot.sim.people.Walker`. The map
    is checked when the simulator loads it: every waypoint and the straight line between
    two must be free space.
    """

    #: Map-frame points ``[x, y]`` or ``[x, y, pause_s]`` (standing ``pause_s`` there on
    #: arrival); it stands at the last one for good, unless ``loop``.
    waypoints: list[list[float]] = Field(min_length=1, max_length=1000)
    #: Walking speed (m/s).
    speed: float = Field(default=1.0, ge=0.1, le=2.5)
    #: Seconds standing at the first waypoint before walking.
    start_delay: float = Field(default=0.0, ge=0, le=86400)
    #: Walk back to the first waypoint and round again, for ever.
    loop: bool = False

    @model_validator(mode="after")
    def _points(self) -> WalkerSettings:
        for index, point in enumerate(self.waypoints):
            if len(point) not in (2, 3):
                raise ValueError(
                    f"waypoint {index} must be [x, y] or [x, y, pause_s], not {len(point)} numbers"
                )
            if not all(math.isfinite(v) for v in point):
                raise ValueError(f"waypoint {index} must be finite numbers")
            if len(point) == 3 and not 0.0 <= point[2] <= 86400:
                raise ValueError(f"waypoint {index}: pause must be 0 … 86400 s, not {point[2]:g}")
        if self.loop and len({(p[0], p[1]) for p in self.waypoints}) < 2:
            raise ValueError("a loop needs two different waypoints")
        return self


class SimSettings(StrictModel):
    """The simulated robot: map, places, speed limits, sensors, battery (SI units)."""

    #: A built-in map name (``"building"``: the 4000 × 4000 default floor, ``"small"``) or a
    #: path to a ROS map_server YAML file.
    map: str = "building"
    #: A places TOML file (``[places.NAME] x, y, yaw_deg``); default: the map's own
    #: ``<map>.places.toml`` beside its YAML, when there is one.
    places: Path | None = None
    #: Where the robot starts: a place name; default: the first place of the map.
    start: str | None = None
    #: Seed for localisation noise; the same seed gives the same run.
    seed: int = 0
    #: Top linear speed (m/s); the paper's robot was limited to 0.5.
    max_linear_speed: float = Field(default=0.5, gt=0, le=HARD_MAX_LINEAR_SPEED)
    #: Top angular speed (rad/s).
    max_angular_speed: float = Field(default=1.0, gt=0, le=HARD_MAX_ANGULAR_SPEED)
    #: Linear acceleration limit (m/s²), used for braking too.
    linear_accel: float = Field(default=0.5, gt=0, le=5.0)
    #: Angular acceleration limit (rad/s²).
    angular_accel: float = Field(default=2.0, gt=0, le=20.0)
    #: Radius of the (round) base; the costmap is inflated by it (m).
    robot_radius: float = Field(default=0.25, gt=0, le=2.0)
    #: A goal is reached within this distance (m) …
    goal_tolerance: float = Field(default=0.05, gt=0, le=1.0)
    #: … and this heading error (degrees), when the goal has a heading.
    yaw_tolerance_deg: float = Field(default=2.0, gt=0, le=45.0)
    #: Control (and laser) rate of the simulation (Hz).
    control_hz: float = Field(default=20.0, ge=5, le=200)
    #: Laser beams over 360° and their range (m).
    laser_beams: int = Field(default=360, ge=8, le=4096)
    laser_range: float = Field(default=10.0, gt=0, le=50.0)
    #: Clearance kept in front of the base beyond its braking distance (m).
    stop_margin: float = Field(default=0.15, ge=0, le=2.0)
    #: How long a goal may stay blocked by an obstacle before it replans (or fails) (s);
    #: the third time in a row in one place it gives up.
    blocked_timeout: float = Field(default=10.0, gt=0, le=600)
    #: The base stops by itself when velocity commands are older than this (s).
    cmd_vel_timeout: float = Field(default=0.5, gt=0, le=5.0)
    #: Localisation noise: standard deviation of position (m) and heading (degrees);
    #: the error is bounded by three standard deviations.
    position_noise: float = Field(default=0.01, ge=0, le=0.5)
    heading_noise_deg: float = Field(default=0.5, ge=0, le=10.0)
    #: Hours the battery lasts standing still, and at full speed.
    battery_idle_hours: float = Field(default=8.0, gt=0)
    battery_moving_hours: float = Field(default=3.0, gt=0)
    #: Charge (percent) below which the battery reports low.
    battery_low_percent: float = Field(default=20.0, ge=0, le=100)
    #: Camera image size (pixels).
    camera_width: int = Field(default=640, ge=32, le=3840)
    camera_height: int = Field(default=480, ge=24, le=2160)
    #: Simulated people walking scripted paths (``[[sim.walkers]]``).
    walkers: list[WalkerSettings] = Field(default_factory=list, max_length=100)


#: A ROS 2 graph name (topic, action, namespace): slash-separated, ROS characters only.
ROS_NAME = r"^/?[A-Za-z_~{}][A-Za-z0-9_/{}~]*$"


class Ros2Settings(StrictModel):
    """The ROS 2 robot (``[robot] kind = "ros2"``): a Nav2 robot reached over rmw_zenoh.

    telebot joins the robot's zenoh network as a client of rmw_zenoh's router (``rmw_zenohd``
    listens on tcp port 7447) and speaks the rmw_zenoh wire format itself: no ROS install.
    Topic and action names are relative to ``namespace`` unless they start with ``/``.
    """

    #: ROS_DOMAIN_ID of the robot's graph (the first chunk of every rmw_zenoh key).
    domain_id: int = Field(default=0, ge=0, le=232)
    #: The ROS 2 distro the robot runs: message type hashes differ between them.
    distro: Literal["jazzy", "kilted"] = "jazzy"
    #: Zenoh endpoints of rmw_zenoh's router (telebot connects as a zenoh client).
    router: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], min_length=1)
    #: Namespace of the robot's topics and actions, and of telebot's own node.
    namespace: str = Field(default="", pattern=r"^(/?[A-Za-z_][A-Za-z0-9_/]*)?$")
    #: Name of telebot's node in the ROS graph (``ros2 node list`` shows it).
    node_name: str = Field(default="telebot", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    #: How long start-up waits for the router and for Nav2's action servers (s).
    connect_timeout: float = Field(default=5.0, gt=0, le=120)
    #: The zenoh link lease telebot's node announces to the router (s): a daemon that
    #: freezes is dropped within it, and the base stops. Longer on a machine whose load
    #: can starve the link's keep-alives for that long (a dropped link fails the goal).
    lease: float = Field(default=0.5, ge=0.1, le=60)
    #: The map frame, and the robot's base frame (for tf when ``pose_topic`` is empty).
    map_frame: str = "map"
    base_frame: str = "base_link"
    map_topic: str = Field(default="map", pattern=ROS_NAME)
    #: PoseWithCovarianceStamped (AMCL); empty: the map -> base frame transform from ``/tf``.
    pose_topic: str = Field(default="amcl_pose", pattern=r"^(/?[A-Za-z_~{}][A-Za-z0-9_/{}~]*)?$")
    odom_topic: str = Field(default="odom", pattern=ROS_NAME)
    scan_topic: str = Field(default="scan", pattern=ROS_NAME)
    battery_topic: str = Field(default="battery_state", pattern=ROS_NAME)
    plan_topic: str = Field(default="plan", pattern=ROS_NAME)
    #: Where the speed cap goes to Nav2's controller (``nav2_msgs/SpeedLimit``, m/s,
    #: transient local): the safety supervisor's cap holds for navigation goals too.
    speed_limit_topic: str = Field(default="speed_limit", pattern=ROS_NAME)
    #: The teleop topic that stop streams zero velocity on.
    cmd_vel_topic: str = Field(default="cmd_vel", pattern=ROS_NAME)
    #: ``geometry_msgs/msg/Twist`` or ``TwistStamped`` on ``cmd_vel_topic`` (Kilted's default
    #: is TwistStamped); default: by distro.
    cmd_vel_stamped: bool | None = None
    navigate_action: str = Field(default="navigate_to_pose", pattern=ROS_NAME)
    drive_action: str = Field(default="drive_on_heading", pattern=ROS_NAME)
    spin_action: str = Field(default="spin", pattern=ROS_NAME)
    #: Camera name -> ``sensor_msgs/msg/CompressedImage`` topic (JPEG or PNG).
    cameras: dict[str, str] = Field(default_factory=dict)
    #: Speed cap telebot enforces on drive_on_heading (m/s); Nav2's own limits apply too.
    max_linear_speed: float = Field(default=0.5, gt=0, le=HARD_MAX_LINEAR_SPEED)
    max_angular_speed: float = Field(default=1.0, gt=0, le=HARD_MAX_ANGULAR_SPEED)
    #: Stop streams zero velocity at this rate (Hz) for ``stop_stream_s`` seconds.
    stop_rate_hz: float = Field(default=20.0, ge=10, le=200)
    stop_stream_s: float = Field(default=1.0, gt=0, le=10)
    #: A map bigger than this many cells is dropped (and logged), never loaded.
    max_map_cells: int = Field(default=64_000_000, ge=1, le=1_000_000_000)
    #: Named places (``[ros2.places.NAME] x, y, yaw_deg``) in the map frame.
    places_file: Path | None = None

    @property
    def twist_stamped(self) -> bool:
        """Whether ``cmd_vel_topic`` carries TwistStamped (explicit, else the distro's)."""
        if self.cmd_vel_stamped is not None:
            return self.cmd_vel_stamped
        return self.distro == "kilted"


Model = TypeVar("Model", bound=BaseModel)


def format_validation_error(exc: ValidationError, source: str) -> str:
    """One line naming the file, the key and what is wrong with it."""
    problems = []
    for err in exc.errors():
        key = ".".join(str(part) for part in err["loc"]) or "(top level)"
        message = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        problems.append(f"{key}: {message}")
    return f"{source}: " + "; ".join(problems)


def load_toml(path: Path, model: type[Model]) -> Model:
    """Read ``path`` as TOML and validate it as ``model``; any problem is a ConfigError."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such file") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from exc
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, str(path))) from exc


def default_home(kind: Literal["robot", "user"]) -> Path:
    """Where keys, contacts and known robots live when ``--home`` is not given.

    ``$TELEBOT_HOME`` if set, else ``<user config dir>/telebot/<kind>`` (robot and user
    keep separate homes, so one machine can run both).
    """
    env = os.environ.get("TELEBOT_HOME")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CONFIG_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".config"
    return base / "telebot" / kind


class AppConfig(StrictModel):
    """The config file of ``telebot-robot`` and ``telebot-user`` (``configs/*.toml``)."""

    #: First chunk of every key expression; robots and users meet only in the same one.
    namespace: str = Field(default="telebot", pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
    transport: TransportSettings = Field(default_factory=TransportSettings)
    call: CallSettings = Field(default_factory=CallSettings)
    #: The user's side: calling the robot again after a drop (the robot ignores it).
    reconnect: ReconnectSettings = Field(default_factory=ReconnectSettings)
    #: The user's side: the fleet page (the robot ignores it).
    fleet: FleetSettings = Field(default_factory=FleetSettings)

    @model_validator(mode="after")
    def _fit_lease(self) -> Self:
        self.fit_lease()
        return self

    def fit_lease(self) -> None:
        """Tell the zenoh settings the call's timeout: a dialling session's default lease
        outlives it (twice it), so the link does not drop while the call still waits
        (:attr:`ZenohSettings.dial_lease`). Run on validation, and again by whoever changes
        ``[call] timeout`` afterwards."""
        self.transport.zenoh._call_timeout = self.call.timeout


class ServiceSettings(StrictModel):
    """Rates of the robot's streaming services."""

    #: Pose, velocity and status updates per second on the ``pose`` channel.
    pose_hz: float = Field(default=10.0, gt=0, le=100)
    #: Telemetry messages per second on the ``telemetry`` channel.
    telemetry_hz: float = Field(default=1.0, gt=0, le=20)


class VideoConfig(StrictModel):
    """The video each call gets from the robot's active camera (JPEG over BULK datagrams)."""

    width: int = Field(default=640, ge=16, le=4096)
    height: int = Field(default=480, ge=16, le=4096)
    #: Frame rate ceiling; the rate follows the link below it.
    max_fps: float = Field(default=30.0, gt=0, le=30)
    #: JPEG quality on a good link (1..100); it drops on a poor one.
    quality: int = Field(default=80, ge=30, le=100)
    #: False: fixed rate and quality whatever the link does.
    adaptive: bool = True


class MediaConfig(StrictModel):
    """``[media]``: the call's video codec, the robot's microphone and speaker, its voice
    (see :mod:`telebot.services.media.robot`, ``docs/protocol.md`` §25)."""

    #: Video codec the robot prefers; a user that cannot take it gets another it can
    #: (JPEG for old clients).
    codec: Literal["h264", "vp8", "jpeg"] = "h264"
    #: Bit rate bounds of H.264 / VP8 (bits/s); the rate follows the link between them.
    min_bitrate: int = Field(default=150_000, ge=50_000, le=20_000_000)
    max_bitrate: int = Field(default=1_500_000, ge=50_000, le=20_000_000)
    #: Seconds between periodic keyframes (more come when a user lost one).
    keyframe_interval: float = Field(default=3.0, ge=0.5, le=60)
    #: Microphone: "tone:440" (a test tone), "wav:PATH" (looped), "default" (sound card,
    #: needs telebot[audio]) or "none".
    mic: str = "tone:440"
    #: Speaker for the user's voice: "wav:PATH", "default", "none".
    speaker: str = "none"
    #: Speak chat replies: "off", "user" (into the user's audio), "speaker", "both".
    voice: Literal["off", "user", "speaker", "both"] = "user"
    #: The speech command; the text is appended, it writes a WAV to stdout.
    voice_command: list[str] = Field(default_factory=lambda: ["espeak-ng", "--stdout"])
    #: Stamp frame numbers into the video (tests, bench); None: on the simulator only.
    stamp: bool | None = None
    #: Shared-memory ring of the user's decoded camera pictures ("" for none).
    user_video_ring: str = ""

    @model_validator(mode="after")
    def _check(self) -> MediaConfig:
        if self.min_bitrate > self.max_bitrate:
            raise ValueError("media: min_bitrate is above max_bitrate")
        for name, spec in (("mic", self.mic), ("speaker", self.speaker)):
            kind = spec.partition(":")[0]
            if kind not in ("tone", "wav", "default", "none", "memory"):
                raise ValueError(f"media: {name} = {spec!r}; use tone:HZ, wav:PATH, default, none")
        return self


class ScreenSettings(StrictModel):
    """The robot's own screen (``[screen]``): a local page showing the remote user's video.

    ``telebot-robot run`` serves it at ``http://HOST:PORT/`` for a browser on the robot's
    display (kiosk mode); a port already taken is a warning, the robot runs on without it.
    """

    enabled: bool = True
    #: Loopback by default: the page shows the user's face and plays their voice.
    host: str = "127.0.0.1"
    port: int = Field(default=8090, ge=0, le=65535)


class GatewaySettings(StrictModel):
    """The robot's own browser gateway (``[gateway]``, docs/protocol.md §26): off unless the
    section is there.

    ``telebot-robot run`` then serves the web app and the gateway at
    ``https://LISTEN:PORT/`` and admits the robot's contacts (and invites). Without
    ``cert``/``key`` it makes a self-signed certificate under the robot's home once.
    """

    enabled: bool = True
    listen: str = "0.0.0.0"
    port: int = Field(default=8443, ge=1, le=65535)
    #: PEM certificate (its chain may follow) and private key; relative to the robot's home.
    cert: Path | None = None
    key: Path | None = None

    @model_validator(mode="after")
    def _cert_and_key(self) -> GatewaySettings:
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together (or neither: a self-signed one)")
        return self


class RobotSettings(StrictModel):
    """Which robot adapter ``telebot-robot run`` drives (``kind``), python-can style.

    ``"sim"`` (default) is the simulated robot, set up by ``[sim]``; third-party adapters
    register in the entry-point group ``telebot.robots`` and read ``options``.
    """

    kind: str = "sim"
    #: Settings for a third-party robot adapter, passed through as they are.
    options: dict[str, Any] = Field(default_factory=dict)


class SafetySettings(StrictModel):
    """The safety supervisor. Its deadman time is ``call.timeout``, its hard speed cap the
    robot's top speed (``sim.max_linear_speed`` on the simulator)."""

    #: Allow cameras other than the navcam while the robot moves.
    usercam_while_moving: bool = False
    #: No driving blind: while the drive holder watches the robot's video, a picture this
    #: old (s; its receiver's reports show no new frame) stops a moving robot and latches
    #: (code ``video_stale``); from half this age the speed cap falls to 0. 0 turns it off.
    stale_video: float = Field(default=1.0, ge=0, le=60)
    #: Audit log (JSON lines); relative paths are taken from the robot's home directory.
    audit_log: Path = Path("audit.jsonl")


class FollowSettings(StrictModel):
    """``[follow]``: the follow-me primitive (``follow`` chat command, :mod:`telebot.robot.follow`).

    Distances are between the centres of the robot and the person (metres).
    """

    #: Distance the robot keeps behind the person.
    distance: float = Field(default=1.2, gt=0.3, le=5.0)
    #: Closer than this the robot stops and the follow ends ("person too close").
    min_distance: float = Field(default=0.6, gt=0.2, le=3.0)
    #: Top speed while following (m/s); the safety cap and the robot's own limit still apply.
    max_speed: float = Field(default=0.5, gt=0, le=HARD_MAX_LINEAR_SPEED)
    #: A person unseen (or seen only jumping) this long is lost: the follow ends (s).
    lost_after: float = Field(default=1.0, gt=0, le=10.0)
    #: A track that moves further than this from where it should be between two updates is
    #: a detector error: the jump is ignored, never followed (m).
    max_jump: float = Field(default=0.8, gt=0, le=5.0)
    #: A person slower than this stands: the robot stops too (m/s).
    standing_speed: float = Field(default=0.15, gt=0, le=1.0)
    #: Held up by an obstacle this long while the person walks on: the follow ends (s).
    obstacle_timeout: float = Field(default=2.0, gt=0, le=60.0)
    #: ``follow`` with no id picks the nearest person within this range (m) …
    start_range: float = Field(default=5.0, gt=0, le=20.0)
    #: … and this angle either side of the robot's heading (degrees).
    front_angle_deg: float = Field(default=60.0, gt=0, le=180.0)

    @model_validator(mode="after")
    def _min_below_distance(self) -> FollowSettings:
        if self.min_distance >= self.distance:
            raise ValueError(
                f"min_distance ({self.min_distance:g} m) must be below distance "
                f"({self.distance:g} m)"
            )
        return self


class DriveSettings(StrictModel):
    """``[drive]``: driving by hand (the ``drive`` channel, :mod:`telebot.services.drive.robot`)."""

    #: The robot obeys only while fresh commands arrive: none for this long (s) and it
    #: stops (not latched; the user's client repeats them at 20 Hz).
    stale_after: float = Field(default=0.3, ge=0.1, le=2.0)


#: The streams ``[recording] streams`` may name: the robot's JSON channels.
RecordedStream = Literal["pose", "telemetry", "plan", "goals", "chat", "safety"]
ALL_RECORDED: tuple[RecordedStream, ...] = ("pose", "telemetry", "plan", "goals", "chat", "safety")


class RecordingSettings(StrictModel):
    """``[recording]``: MCAP files of every call on the robot (see
    :mod:`telebot.services.recording`), each finished (readable) at a call's end, after
    ``max_seconds`` or past ``max_bytes``."""

    #: Off by default: recordings hold what users typed and where the robot went.
    enabled: bool = False
    #: Folder of the files; None: the audit log's folder. Relative: from the robot's home.
    dir: Path | None = None
    #: A file that grows past this many bytes is finished and the next one begun.
    max_bytes: int = Field(default=64 * 1024 * 1024, ge=4096)
    #: A file is finished at the latest this many seconds after it was begun (and at each
    #: call's end), so that a long call is readable without stopping the robot.
    max_seconds: float = Field(default=300.0, gt=0, le=86400)
    #: How many files are kept (the oldest are deleted), the one being written included.
    keep: int = Field(default=1000, ge=1, le=100000)
    #: How many bytes of files are kept at most (the oldest are deleted).
    keep_bytes: int = Field(default=1024 * 1024 * 1024, ge=4096)
    #: Which channels of each call are recorded (both ways); call starts and ends and
    #: safety events (the audit records) always are.
    streams: list[RecordedStream] = Field(default_factory=lambda: list(ALL_RECORDED))


#: Topics an observer may relay by default: what the robot shows anyway (no cameras
#: beyond the video it already gets, no parameters, no logs).
SAFE_OBSERVER_TOPICS = (
    "/scan",
    "/odom",
    "/amcl_pose",
    "/plan",
    "/map",
    "/tf",
    "/tf_static",
    "/battery_state",
)


class RelaySettings(StrictModel):
    """The topic relay (``relay`` service): which topics each role may relay, and limits.

    Patterns are shell globs (``fnmatch``) on fully qualified topic names (``/scan``,
    ``/*/image/compressed``); ``*`` also matches ``/``. Admins may relay what drivers may.
    """

    #: Topics a driver (and an admin) may relay.
    driver: list[str] = Field(default_factory=lambda: ["*"])
    #: Topics an observer may relay.
    observer: list[str] = Field(default_factory=lambda: list(SAFE_OBSERVER_TOPICS))
    #: Relays one call may have at once.
    max_relays: int = Field(default=16, ge=1, le=256)
    #: Bytes per second all relays of one call may send (fragments are paced to it, so
    #: large messages never crowd out control; messages beyond it are dropped and counted).
    max_bytes_per_second: float = Field(default=8_000_000.0, gt=0)
    #: Messages per second a relay sends at most when the user asks for no rate.
    max_rate: float = Field(default=100.0, gt=0, le=1000)


class PeopleSettings(StrictModel):
    """``[people]``: person detection, tracking, the ``people`` stream and its alerts.

    See :mod:`telebot.robot.perception` and ``docs/protocol.md`` (the ``people`` channel).
    """

    #: Detect and track people at all (off: the stream sends no tracks, no alerts).
    enabled: bool = True
    #: Laser scans looked at per second.
    scan_hz: float = Field(default=10.0, gt=0, le=50)
    #: Camera frames run through the HOG person detector per second (0: laser only).
    camera_hz: float = Field(default=2.0, ge=0, le=30)
    #: The camera the detector looks through.
    camera: str = "navcam"
    #: Rate of the ``people`` stream to each user (Hz).
    stream_hz: float = Field(default=5.0, gt=0, le=20)
    #: Someone closing in within this distance (m) raises "person approaching from …".
    alert_distance: float = Field(default=2.5, gt=0, le=10.0)
    #: Someone standing this close (m) in front of the usercam …
    screen_distance: float = Field(default=1.5, gt=0, le=5.0)
    #: … for this long (s) raises "someone is in front of the screen".
    screen_seconds: float = Field(default=1.5, ge=0, le=60.0)


class RobotConfig(AppConfig):
    """The config file of ``telebot-robot`` (``configs/robot.toml``): adds the robot."""

    robot: RobotSettings = Field(default_factory=RobotSettings)
    sim: SimSettings = Field(default_factory=SimSettings)
    ros2: Ros2Settings = Field(default_factory=Ros2Settings)
    services: ServiceSettings = Field(default_factory=ServiceSettings)
    safety: SafetySettings = Field(default_factory=SafetySettings)
    video: VideoConfig = Field(default_factory=VideoConfig)
    media: MediaConfig = Field(default_factory=MediaConfig)
    recording: RecordingSettings = Field(default_factory=RecordingSettings)
    relay: RelaySettings = Field(default_factory=RelaySettings)
    follow: FollowSettings = Field(default_factory=FollowSettings)
    drive: DriveSettings = Field(default_factory=DriveSettings)
    people: PeopleSettings = Field(default_factory=PeopleSettings)
    screen: ScreenSettings = Field(default_factory=ScreenSettings)
    #: None (no ``[gateway]`` section): no browser gateway.
    gateway: GatewaySettings | None = None
