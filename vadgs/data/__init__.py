"""Scene loaders: the benchmark scene format, COLMAP reconstructions and TRI's DGP format."""

__all__: list[str] = []
