"""The v2 Wi-Fi build's UDP discovery on loopback: the reply format, the id collision, etactilekit://ID."""

from __future__ import annotations

import socket

import pytest

from tactdeform_hw.device.driver.wifi_discovery import discover, parse_reply, resolve
from tactdeform_hw.emulator.serving.udp_discovery import DiscoveryResponder, device_id_from_mac, reply_for
from tactdeform_hw.errors import ConfigurationError


def test_the_id_is_the_oui_reversed_so_espressif_boards_collide() -> None:
    a = device_id_from_mac(bytes.fromhex("dc5475c1a2b3"))
    b = device_id_from_mac(bytes.fromhex("dc5475000001"))
    assert a == b == "7554DC"


def test_reply_format_and_parse() -> None:
    data = reply_for("7554DC", "192.168.4.1", mode="AP")
    assert data == b"ETK!;id=7554DC;name=etactilekit-7554DC;ip=192.168.4.1;port=8080;mode=AP;fw=1.0"
    kit = parse_reply(data)
    assert kit is not None and kit.url == "socket://192.168.4.1:8080" and kit.mode == "AP"
    assert parse_reply(b"hello") is None


def test_discovery_on_loopback_answers_only_etk_queries() -> None:
    with DiscoveryResponder("ABC123", port=0, tcp_port=18080) as r:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.sendto(b"nope", r.address)
        s.close()
        kits = discover([r.address], listen_s=0.2, bursts=2)
        assert [(k.id, k.ip, k.port) for k in kits] == [("ABC123", "127.0.0.1", 18080)]
        assert r.queries == 2 and r.ignored >= 1


def test_colliding_ids_are_refused_not_guessed() -> None:
    shared = device_id_from_mac(bytes.fromhex("dc5475c1a2b3"))
    with (
        DiscoveryResponder(shared, port=0, tcp_port=18081) as r1,
        DiscoveryResponder(shared, port=0, tcp_port=18082) as r2,
    ):
        kits = discover([r1.address, r2.address], listen_s=0.2, bursts=1)
        assert len(kits) == 2
        with pytest.raises(ConfigurationError, match="2 kits answer to id '7554DC'"):
            resolve(shared, kits)
    with pytest.raises(ConfigurationError, match="no kit with id 'FFFFFF'"):
        resolve("FFFFFF", kits)


def test_etactilekit_url_resolves_to_pyserials_socket_handler() -> None:
    from tactdeform_hw.device.driver.serial_driver import open_port

    listener = socket.create_server(("127.0.0.1", 0))
    tcp_port = listener.getsockname()[1]
    with listener, DiscoveryResponder("C0FFEE", port=0, tcp_port=tcp_port) as r:
        port = open_port(f"etactilekit://C0FFEE?discovery=127.0.0.1:{r.address[1]}", timeout=0.5)
        assert port.port == f"socket://127.0.0.1:{tcp_port}"
        port.open()
        conn, _ = listener.accept()
        port.write(b"\xf4")
        assert conn.recv(1) == b"\xf4"
        conn.close()
        port.close()
    with pytest.raises(ConfigurationError, match="unknown option"):
        open_port("etactilekit://C0FFEE?x=1")


def test_ports_lists_discovered_kits(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.cli import main

    with DiscoveryResponder("ABC123", port=0, tcp_port=18083) as r:
        assert main(["ports", "--no-usb", "--wifi", f"127.0.0.1:{r.address[1]}"]) == 0
    out = capsys.readouterr().out
    assert "etactilekit://ABC123" in out and "127.0.0.1:18083" in out


def test_a_responder_on_every_interface_advertises_the_address_facing_the_requester() -> None:
    """Bound to 0.0.0.0 the reply's ip= is where the requester can connect (here loopback), never
    0.0.0.0."""
    with DiscoveryResponder("ABC123", host="0.0.0.0", port=0, tcp_port=18084) as r:
        kits = discover([("127.0.0.1", r.address[1])], listen_s=0.2, bursts=1)
    assert r.address[0] == "0.0.0.0"
    assert [(k.ip, k.port) for k in kits] == [("127.0.0.1", 18084)]
    assert kits[0].url == "socket://127.0.0.1:18084"


def test_ports_with_only_a_wifi_kit_does_not_say_none_was_found(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main
    from tactdeform_hw.device.driver import discovery

    monkeypatch.setattr(discovery, "serial_candidates", lambda *a, **k: [])  # no serial port here
    with DiscoveryResponder("ABC123", port=0, tcp_port=18085) as r:
        assert main(["ports", "--no-usb", "--wifi", f"127.0.0.1:{r.address[1]}"]) == 0
    out = capsys.readouterr().out
    assert "etactilekit://ABC123" in out and "no candidate boards found" not in out
    assert out.index("DEVICE") < out.index("etactilekit://ABC123")  # the header heads the kit's row
    assert "1 Wi-Fi kit(s) answered discovery" in out


def test_ports_with_no_kit_answering_says_where_it_asked(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main
    from tactdeform_hw.device.driver import discovery

    monkeypatch.setattr(discovery, "serial_candidates", lambda *a, **k: [])
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    with silent:
        port = silent.getsockname()[1]
        assert main(["ports", "--no-usb", "--wifi", f"127.0.0.1:{port}"]) == 0
    out = capsys.readouterr().out
    assert "no candidate boards found" in out
    assert f"no Wi-Fi kit answered discovery (sent ETK? to UDP 127.0.0.1:{port} 2 time(s)" in out


def test_etactilekit_url_that_finds_no_kit_names_where_and_how_long_it_asked() -> None:
    from tactdeform_hw.device.driver.serial_driver import open_port

    with DiscoveryResponder("ABC123", port=0, tcp_port=18086) as r:
        with pytest.raises(ConfigurationError) as info:
            open_port(f"etactilekit://C0FFEE?discovery=127.0.0.1:{r.address[1]}", timeout=0.5)
    msg = str(info.value)
    assert f"UDP 127.0.0.1:{r.address[1]}" in msg
    assert "2 time(s), listening 0.3 s after each (0.6 s in all)" in msg
    assert "kits answered with id(s) ABC123" in msg and "?discovery=HOST:PORT" in msg
