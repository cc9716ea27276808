"""facecast.client: thin clients (asyncio Python client, CLI commands, static web viewer). Never imports server."""
