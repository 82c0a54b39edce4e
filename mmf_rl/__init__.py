"""mmf-rl: multimodal forecasters that stay accurate when sensors go missing."""

__version__ = "0.1.0"
