"""Publishing a station message: every type in ``lcm_messages`` carries
``sent_wall_utime``, the Unix time (us) it left its sender, so a receiver on a
clock kept in step (the same host, or PTP) measures the latency the link added."""

import time


def publish(lcm, channel: str, message) -> None:
    """Stamp ``message.sent_wall_utime`` with the wall clock and publish it on ``lcm``."""
    message.sent_wall_utime = time.time_ns() // 1000
    lcm.publish(channel, message.encode())
