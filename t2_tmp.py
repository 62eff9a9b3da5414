import time
from tactdeform_hw.device.serial_driver import EtactileKitDevice
from tactdeform_hw.device.config import StimConfig
from tactdeform_hw.device.safety import SafetyGuard
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed_v2 import TimedEmulatorV2
class V2Board(TimedEmulatorV2):
    def __init__(self):
        super().__init__()
        self._rx = bytearray()
    def read_tx(self, size=None):
        self._rx += super().read_tx()
        n = len(self._rx) if size is None else min(size, len(self._rx))
        out = bytes(self._rx[:n]); del self._rx[:n]; return out
    @property
    def in_waiting(self):
        self._rx += super().read_tx()
        return len(self._rx)
t=time.time()
emu = V2Board()
port = TimedPort(emu, robust_encoding=False)
guard = SafetyGuard(2000, regions_ua=[400,800,1200,1600,2000,2000,2000,2000,2000])
dev = EtactileKitDevice(port, firmware="v2", guard=guard)
print("open", port.now_s, dev.link_state)
dev.configure(StimConfig(electrode_count=32, current_ua=1500))
print("cfg", port.now_s)
t0 = port.now_s
dev.send_pattern([1]*32)
t1=port.now_s
port.advance(0.05)
print("peak", sorted(emu.peak_current_ua(since_us=t1*1e6).items())[:40])
print(guard.electrode_limits(32))
dev.all_off()
t2=port.now_s
port.advance(0.05)
print("after off", emu.peak_current_ua(since_us=(t2+0.02)*1e6))
dev.close()
print(emu.hazards[-3:], time.time()-t)
