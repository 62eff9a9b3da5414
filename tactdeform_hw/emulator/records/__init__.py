"""What the emulated board tells its user: per-scan, per-pulse and per-command reports, and waveform traces
(VCD, CSV, JSON)."""
