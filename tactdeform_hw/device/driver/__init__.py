"""The driver: the device interface, its transports (pyserial, pyusb, TCP), firmware identification,
pacing, the audit log, and discovery of attached boards."""
