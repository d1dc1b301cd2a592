"""The station service: the running pipeline's metrics and health over HTTP (`bf-epic run --serve`).

:mod:`.monitor` reads the blocks' counters into a snapshot and judges its health (pure functions);
:mod:`.server` serves them with aiohttp and prometheus_client. Nothing here is imported unless a run
asks for the service.
"""
