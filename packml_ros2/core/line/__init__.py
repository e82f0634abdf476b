"""The line: the coordinator's logic as a pure core (no rclpy, the clock passed in) — units and
their order on the line, cell commands, aggregation, interlock propagation — and the line's
performance: stop episodes with their root cause, losses in buckets, OEE, per shift.
"""
