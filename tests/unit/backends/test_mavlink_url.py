"""MAVLink connection URLs in an agent's `backend:` (btmission.backends.mavlink_url)."""

from __future__ import annotations

import pytest

from btmission.backends.mavlink_url import MavlinkAddress, MavlinkUrlError, parse_mavlink_url


@pytest.mark.parametrize(
    ("url", "address", "device"),
    [
        ("mavlink+udp://127.0.0.1:14540", MavlinkAddress("udp", "127.0.0.1", 14540),
         "udpin:127.0.0.1:14540"),
        ("mavlink+udpout://192.168.1.20:14550?sysid=2", MavlinkAddress(
            "udpout", "192.168.1.20", 14550, sysid=2), "udpout:192.168.1.20:14550"),
        ("mavlink+tcp://localhost:5760?sysid=1&compid=1", MavlinkAddress(
            "tcp", "localhost", 5760, sysid=1, compid=1), "tcp:localhost:5760"),
        ("mavlink+tcpin://0.0.0.0:5760", MavlinkAddress("tcpin", "0.0.0.0", 5760),
         "tcpin:0.0.0.0:5760"),
        ("mavlink+udp://[::1]:14540", MavlinkAddress("udp", "::1", 14540), "udpin:::1:14540"),
        ("mavlink+serial:///dev/ttyACM0?baud=921600", MavlinkAddress(
            "serial", device_path="/dev/ttyACM0", baud=921600), "/dev/ttyACM0"),
        ("mavlink+serial:///dev/ttyUSB1", MavlinkAddress("serial", device_path="/dev/ttyUSB1"),
         "/dev/ttyUSB1"),
    ],
)  # fmt: skip
def test_urls_parse_to_addresses_and_pymavlink_devices(
    url: str, address: MavlinkAddress, device: str
) -> None:
    got = parse_mavlink_url(url)
    assert got == address and got.device() == device
    assert parse_mavlink_url(got.url()) == got  # the normalised URL reads back the same


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("mavlink://127.0.0.1:14540", "say the transport in the scheme, e.g. "
         "mavlink+udp://127.0.0.1:14540 (mavlink+udp, mavlink+udpout, mavlink+tcp, "
         "mavlink+tcpin, mavlink+serial)"),
        ("mavlink://udp:127.0.0.1:14540",
         "write the transport in the scheme: mavlink+udp://127.0.0.1:14540"),
        ("mavlink:udpin:0.0.0.0:14550",
         "write the transport in the scheme: mavlink+udp://0.0.0.0:14550"),
        ("mavlink+quic://127.0.0.1:1", "unknown MAVLink transport 'quic' (expected one of: "
         "udp, udpout, tcp, tcpin, serial)"),
        ("mavlink+udp://127.0.0.1", "expected host:port with a port number, e.g. "
         "mavlink+udp://127.0.0.1:14540"),
        ("mavlink+udp://127.0.0.1:", "expected host:port with a port number"),
        ("mavlink+udp://:14540", "the host is missing, e.g. mavlink+udp://127.0.0.1:14540 "
         "(0.0.0.0: every interface)"),
        ("mavlink+udp://127.0.0.1:70000", "port 70000 is out of range (1 to 65535)"),
        ("mavlink+udp://127.0.0.1:0", "port 0 is out of range (1 to 65535)"),
        ("mavlink+udp://bad host:1", "'bad host' is not a host name or an IP address"),
        ("mavlink+udp://[::zz]:1", "'::zz' is not an IPv6 address"),
        ("mavlink+udp://127.0.0.1:14540?sysid=0", "sysid must be a whole number from 1 to 255, "
         "got '0'"),
        ("mavlink+udp://127.0.0.1:14540?sysid=x", "sysid must be a whole number from 1 to 255"),
        ("mavlink+udp://127.0.0.1:14540?compid=256", "compid must be a whole number from 0 to "
         "255, got '256'"),
        ("mavlink+udp://127.0.0.1:14540?baud=57600", "unknown parameter 'baud' (a udp URL "
         "takes: sysid, compid)"),
        ("mavlink+udp://127.0.0.1:14540?sysid=1&sysid=2", "parameter 'sysid' is given twice"),
        ("mavlink+udp://127.0.0.1:14540?sysid", "cannot read the query '?sysid'"),
        ("mavlink+serial://dev/ttyACM0", "a serial URL names the port's path: "
         "mavlink+serial:///dev/ttyACM0?baud=921600"),
        ("mavlink+serial:///dev/ttyACM0?baud=0", "baud must be a whole number from 1 to "
         "10000000, got '0'"),
        ("mavlinkx", "expected a MAVLink URL such as mavlink+udp://127.0.0.1:14540"),
    ],
)  # fmt: skip
def test_bad_urls_say_what_to_write(url: str, message: str) -> None:
    with pytest.raises(MavlinkUrlError) as err:
        parse_mavlink_url(url)
    assert message in str(err.value)
