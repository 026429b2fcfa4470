"""PanoMan (Wang et al., ACM TOG 2021): sparse localized components over RLA vectors of the canonical mesh."""

__all__: list[str] = []
