from ttompc.data.stats import NormStats

__all__ = ["NormStats"]
