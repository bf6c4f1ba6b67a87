"""The browser viewer (``clvol view``): an aiohttp server streaming frames of one
``clvol.Renderer`` to a static page over a WebSocket. See ``docs/viewer.md``."""
