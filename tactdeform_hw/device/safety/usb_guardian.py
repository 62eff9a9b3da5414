"""The guardian of a board opened over USB: it switches the board off when its owner dies without running
code (SIGKILL, a crash in native code).

The serial guardian (:mod:`.guardian`) shares the owner's open file.  A USB interface cannot be shared:
the kernel gives a claim to one process at a time and takes it back when that process's usbfs file
closes — which, for a dead process, is the kernel's own doing, at once.  So the USB guardian is a process
started with the device that:

* runs in its own session and ignores the terminal's signals, exactly as the serial guardian (a Ctrl-C
  or a hang-up reaches the owner's process group, not it);
* has found the very board the owner holds (bus and address) before it says ``ready``, and connected to
  it (libusb, or the server of ``emulate --usb``) — so nothing is left to look up once it must act;
* waits on the owner's pipe, with the owner's orders on it (``stop``, ``off``, ``pace``: the same
  protocol and the same bytes as the serial guardian — v1.2's :func:`~.guardian.stop_packet` and
  :func:`~.guardian.off_packet`, or v2's ``off_packet``);
* when the pipe closes without ``bye``, **claims the CDC interfaces as soon as the owner's claim is gone**
  (retrying a busy claim every 2 ms for up to :data:`CLAIM_BUDGET_S`; if the kernel driver holds them —
  an owner that gave them back on a failed close — it takes them back from it), then sends the stop bytes
  and proves them exactly as the serial guardian does (:func:`~.guardian.switch_off_on`), pulsing the
  reset line (SET_CONTROL_LINE_STATE: RTS without DTR holds the ESP32-S3 in reset) if the firmware never
  answers;
* releases the interfaces and gives them back to the kernel driver where the owner had taken them from it.

An owner that is alive but abandons the board to its guardian (its own all-off failed) releases its
claim first (:meth:`~.usb_transport.UsbCdcPort.release_for_guardian`), so the guardian need not wait.

It is started with ``python -I -S`` on this file, with pyusb's directory on its path: it imports the
standard library, pyusb and two files of this package loaded by path (the serial guardian's stdlib-only
logic and, for the emulated board, :mod:`tactdeform_hw.emulator.serving.usb_client`) — not the package.
"""

from __future__ import annotations

import errno
import os
import sys
import time
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tactdeform_hw.device.safety.guardian import Guardian

#: How long the guardian keeps trying to claim an interface the dead owner's claim still holds.
CLAIM_BUDGET_S = 1.0
_CLAIM_RETRY_S = 0.002
_CDC_SET_CONTROL_LINE_STATE = 0x22
_REQ_OUT_CLASS_INTERFACE = 0x21
_HERE = os.path.dirname(os.path.abspath(__file__))


# --- owner side ------------------------------------------------------------------------------------------


def start_usb_guardian(
    name: str,
    *,
    backend: str,
    bus: int,
    address: int,
    vid: int,
    pid: int,
    comm_interface: int | None,
    data_interface: int,
    ep_out: int,
    ep_in: int,
    packet_size: int,
    give_back: list[int],
    stop: bytes | None = None,
    release_owner: Callable[[], None] | None = None,
    ready_timeout_s: float = 10.0,
) -> Guardian:
    """Start the USB guardian for the board at ``bus``/``address`` (``backend``: ``"libusb"`` or
    ``"emulator:PATH"``).  ``give_back``: the interfaces the owner detached the kernel driver from."""
    import usb

    from tactdeform_hw.device.safety.guardian import Guardian, GuardianError, stop_packet

    stop = stop_packet() if stop is None else stop
    usb_path = os.path.dirname(os.path.dirname(os.path.abspath(usb.__file__)))
    cmd = [sys.executable, "-I", "-S", os.path.abspath(__file__), "--sys-path", usb_path]
    cmd += ["--backend", backend, "--bus", str(bus), "--address", str(address)]
    cmd += ["--vid", str(vid), "--pid", str(pid), "--data", str(data_interface)]
    cmd += ["--ep-out", str(ep_out), "--ep-in", str(ep_in), "--packet", str(packet_size)]
    cmd += ["--give-back", ",".join(str(n) for n in give_back), "--name", name, "--stop", stop.hex()]
    if comm_interface is not None:
        cmd += ["--comm", str(comm_interface), "--reset-line"]
    try:
        return Guardian.spawn(cmd, name, ready_timeout_s=ready_timeout_s, release_owner=release_owner)
    except GuardianError:
        raise
    except OSError as exc:
        raise GuardianError(f"cannot start the guardian for {name}: {exc}") from exc


# --- guardian side (stdlib and pyusb only) ------------------------------------------------------------------


def _load(filename: str, module_name: str) -> ModuleType:
    """A file of this package as a module of its own (the package itself is never imported here)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(module_name, filename)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses and typing look their module up by name
    spec.loader.exec_module(module)
    return module


def _guardian() -> ModuleType:
    """The serial guardian's stdlib-only logic (``guardian.py``), loaded by path once: this file runs as a
    script, outside the package, and shares with it how replies are read and how orders are carried out."""
    module = sys.modules.get("_etk_guardian")
    return module if module is not None else _load(os.path.join(_HERE, "guardian.py"), "_etk_guardian")


def libusb1_backend() -> Any:
    """pyusb's libusb 1.0 backend, else the one of the DLL shipped by the ``libusb-package`` wheel (pyusb
    does not look there by itself); None when there is neither.  The owner's transport
    (:func:`~.usb_transport.default_backend`) and its guardian look the bus up this same way."""
    import usb.backend.libusb1 as libusb1

    backend = libusb1.get_backend()
    if backend is None:
        try:
            import libusb_package

            backend = libusb_package.get_libusb1_backend()
        except (ImportError, OSError, AttributeError):
            backend = None
    return backend


def _backend(how: str) -> Any:
    if how.startswith("emulator:"):
        package = os.path.dirname(os.path.dirname(_HERE))
        client = _load(os.path.join(package, "emulator", "serving", "usb_client.py"), "_etk_usb_client")
        return client.EmulatorClientBackend(how[len("emulator:") :])
    return libusb1_backend()


class UsbLink:
    """The board's CDC data endpoints, once the guardian has claimed them (see
    :class:`~.guardian.GuardianLink`)."""

    def __init__(self, dev: Any, ep_out: int, ep_in: int, comm: int | None, packet_size: int) -> None:
        import usb.core

        self.core = usb.core
        self.dev = dev
        self.ep_out, self.ep_in, self.comm = ep_out, ep_in, comm
        self.packet_size = packet_size

    def discard_output(self) -> bool:
        """Nothing to do: the kernel cancelled the dead owner's transfers with it."""
        return True

    def wait_sent(self, deadline: float) -> None:
        return None  # nothing of the owner's is left to send

    def _read_packet(self, timeout_ms: int) -> bytes:
        try:
            return bytes(self.dev.read(self.ep_in, self.packet_size, max(1, timeout_ms)).tobytes())
        except self.core.USBTimeoutError:
            return b""
        except self.core.USBError as exc:
            if getattr(exc, "errno", None) == errno.EPIPE:
                try:
                    self.dev.clear_halt(self.ep_in)
                except self.core.USBError:
                    pass
            return b""

    def discard_input(self) -> None:
        for _ in range(64):
            if not self._read_packet(1):
                return

    def write(self, data: bytes, deadline: float) -> bool:
        for start in range(0, len(data), self.packet_size):
            pkt = data[start : start + self.packet_size]
            for attempt in (1, 2):
                left_ms = int((deadline - time.monotonic()) * 1000)
                if left_ms <= 0:
                    return False
                try:
                    if self.dev.write(self.ep_out, pkt, left_ms) != len(pkt):
                        return False
                    break
                except self.core.USBTimeoutError:
                    return False
                except self.core.USBError as exc:
                    if getattr(exc, "errno", None) != errno.EPIPE or attempt == 2:
                        return False
                    try:
                        self.dev.clear_halt(self.ep_out)
                    except self.core.USBError:
                        return False
        return True

    def read_reply(self, timeout_s: float) -> bytes:
        """What the board answers within ``timeout_s``, read until it has been quiet for 3 ms."""
        got: bytes = _guardian().read_until_quiet(
            lambda left_s: self._read_packet(int(left_s * 1000) or 1), timeout_s
        )
        return got

    def pulse_reset(self) -> bool:
        """RTS without DTR for 100 ms: the USB Serial/JTAG controller holds the chip in reset."""
        if self.comm is None:
            return False
        try:
            for value, hold_s in ((0x02, 0.1), (0x00, 0.0)):
                self.dev.ctrl_transfer(
                    _REQ_OUT_CLASS_INTERFACE, _CDC_SET_CONTROL_LINE_STATE, value, self.comm, None, 1000
                )
                time.sleep(hold_s)
        except self.core.USBError:
            return False
        return True


def claim(dev: Any, interfaces: list[int], budget_s: float = CLAIM_BUDGET_S) -> str | None:
    """Claim ``interfaces`` as soon as the owner's claim is gone; None, or why it could not."""
    import usb.core
    import usb.util

    deadline = time.monotonic() + budget_s
    for n in interfaces:
        while True:
            try:
                usb.util.claim_interface(dev, n)
                break
            except usb.core.USBError as exc:
                busy = getattr(exc, "errno", None) == errno.EBUSY
                if busy and _kernel_driver_active(dev, n):
                    try:  # the owner gave it back to the kernel on a failed close: it is still its board
                        dev.detach_kernel_driver(n)
                        continue
                    except usb.core.USBError:
                        pass
                if not busy or time.monotonic() >= deadline:
                    return f"cannot claim interface {n}: {exc}"
                time.sleep(_CLAIM_RETRY_S)
    return None


def _kernel_driver_active(dev: Any, n: int) -> bool:
    import usb.core

    try:
        return bool(dev.is_kernel_driver_active(n))
    except (usb.core.USBError, NotImplementedError):
        return False


def _give_back(dev: Any, interfaces: list[int], give_back: list[int]) -> None:
    import usb.core
    import usb.util

    for n in interfaces:
        try:
            usb.util.release_interface(dev, n)
        except (usb.core.USBError, ValueError):
            pass
    for n in give_back:
        try:
            dev.attach_kernel_driver(n)
        except (usb.core.USBError, NotImplementedError):
            pass
    try:
        usb.util.dispose_resources(dev)
    except usb.core.USBError:
        pass


def main(argv: list[str]) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="tactdeform-hw-usb-guardian")
    ap.add_argument("--sys-path", default="")
    ap.add_argument("--backend", required=True)
    for option in ("--bus", "--address", "--vid", "--pid", "--data", "--ep-out", "--ep-in", "--packet"):
        ap.add_argument(option, type=int, required=True)
    ap.add_argument("--comm", type=int, default=None)
    ap.add_argument("--give-back", default="")
    g = _guardian()
    g.add_owner_arguments(ap)
    a = ap.parse_args(argv)
    if a.sys_path:
        sys.path.insert(0, a.sys_path)
    g.ignore_terminal_signals()
    try:
        import usb.core
    except ImportError as exc:
        print(f"cannot import pyusb: {exc}", flush=True)
        return 1
    try:
        backend = _backend(a.backend)
        dev = usb.core.find(
            backend=backend,
            idVendor=a.vid,
            idProduct=a.pid,
            custom_match=lambda d: d.bus == a.bus and d.address == a.address,
        )
    except (OSError, usb.core.USBError) as exc:
        print(f"cannot reach the board: {exc}", flush=True)
        return 1
    if dev is None:
        print(f"no USB device {a.vid:04x}:{a.pid:04x} at bus {a.bus} address {a.address}", flush=True)
        return 1
    g.say_ready()
    orders = g.watch_owner(a.owner_fd, bytes.fromhex(a.stop))
    if orders is None:
        return 0
    interfaces = ([a.comm] if a.comm is not None else []) + [a.data]
    give_back = [int(n) for n in a.give_back.split(",") if n]
    why = claim(dev, interfaces)
    if why is not None:
        g.say(a.name, f"owner (pid {a.owner_pid}) gone, but NOTHING SENT: {why}; unplug the board")
        return 2
    link = UsbLink(dev, a.ep_out, a.ep_in, a.comm, a.packet)
    how: str = orders.carry_out(link, reset_line=a.reset_line, name=a.name)
    _give_back(dev, interfaces, give_back)
    return int(g.report_gone(a.name, a.owner_pid, how))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
