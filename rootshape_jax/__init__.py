"""rootshape_jax."""
