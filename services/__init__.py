"""Property Service core and the services themselves."""
