"""HTTP routes, one module per resource. Thin: validate, call a function, shape a response."""
