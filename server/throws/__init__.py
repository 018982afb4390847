"""Throws: targets, the preview gate, previews, starting a throw, the history, and their routes."""
