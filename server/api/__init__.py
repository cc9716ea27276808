"""The HTTP/WebSocket API: ``create_app(config)`` builds the FastAPI application."""
