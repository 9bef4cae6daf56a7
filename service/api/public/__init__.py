"""The public shapes (the Public schema family), one module per concept, at the API's edge: routes, SSE
events and the CLI answer with these models, so /docs shows every field. Each is built from what the
layers below keep: a result from its row (service/store/result_rows.py makes the row), a map from its
view (service/maps/view.py), jobs, sweeps, validations and schedules from their rows, read through the
service layer's `Records` (the storage's reads). No module below the API imports these.
"""
