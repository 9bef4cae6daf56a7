"""One router per resource (thin: validate, call the service layer, return its Public model)."""

from service.api.routes import bench, catalog, events, jobs, maps, results, runups, schedules, sweeps

ROUTERS = [
    bench.router,
    jobs.router,
    results.router,
    sweeps.router,
    schedules.router,
    maps.router,
    runups.router,
    events.router,
    catalog.router,
]
