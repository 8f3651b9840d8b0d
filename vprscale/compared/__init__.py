"""The methods CoarseHash is compared with (docs/method.md: the baseline)."""
