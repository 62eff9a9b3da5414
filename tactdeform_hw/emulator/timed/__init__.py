"""The time model: the firmware model on a simulated clock (link and receive queue, the parser's rhythm, the
scan timer, the watchdog), its timing constants, and a per-cycle analytic engine for long runs."""
