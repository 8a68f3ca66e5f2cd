"""What each service process tells about itself when asked (`tether status`): where it runs, what it holds."""

from __future__ import annotations

from typing import Annotated

from msgspec import Meta

from schemas.common import Frozen, Name

Bytes = Annotated[int, Meta(ge=0)]
Duration = Annotated[float, Meta(ge=0.0)]


class ProcessStatus(Frozen):
    """One service's process now, as its kernel counts it (the service may run on another host)."""

    service: Name
    host: Annotated[str, Meta(max_length=255)]
    pid: Annotated[int, Meta(ge=1)]
    rss_bytes: Bytes  # resident memory now (VmRSS)
    peak_rss_bytes: Bytes  # the most it has held resident (VmHWM)
    cpu_seconds: Duration  # user + system, all its threads, since it started
    uptime_seconds: Duration  # since the service's runtime was loaded
    # What the processes it started hold resident (VmRSS summed): the sim's camera renderer.
    children_rss_bytes: Bytes = 0
