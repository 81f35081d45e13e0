"""The web dashboard the orchestrator serves at ``/``: server-rendered pages (Jinja2), htmx for
partial updates and server-sent events, uPlot for the interactive plots.

Every script and style is served from this package (``static/``; the third-party files in
``static/vendor/`` with their licenses), so the dashboard works offline. Pages read through
the same store as the REST API; the actions that change state (create, cancel, delete) are
the REST API's own routes, called by the page with the bearer token the user gives once.

* ``data``: pure functions from database rows to what the pages show;
* ``routes``: the pages, their fragments and their event streams (not in the OpenAPI schema);
* ``bench``: page weight, first paint and render time (``ra2vipas bench dashboard``).
"""
