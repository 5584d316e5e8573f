"""Developer tools (not shipped behaviour): README screenshots, model builders, browser."""
