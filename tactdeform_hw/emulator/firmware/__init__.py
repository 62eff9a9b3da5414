"""The firmware model: what the eTactileKit firmware stores, parses and scans, per firmware version, and the
board it drives (HV513 chains, DAC, skin).  No clock here: the time model in :mod:`..timed` runs it."""
