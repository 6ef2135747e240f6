"""HTTP layer: dependencies, the error mapping and the routes by resource."""
