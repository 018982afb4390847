"""Evaluation: the paper's protocol, the site matrix, the deploy comparison, the Drake check and
`slinger evaluate`."""
