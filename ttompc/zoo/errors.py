"""Errors of reading cards and of fetching and publishing zoo files, shared by the cards (``cards``, ``evaluations``),
the URL downloads (``download``), the Hugging Face Hub (``hub``) and publishing (``publish``). All are
``UserError``s: one line, exit code 2 on the command line."""

from __future__ import annotations

from ttompc.errors import UserError


class DownloadError(UserError, RuntimeError):
    """A file that could not be fetched."""


class ChecksumError(DownloadError):
    """Fetched bytes that are not the published ones (the file has been deleted)."""


class PublishError(UserError, RuntimeError):
    """A publish request that cannot be carried out as asked."""


class CardError(UserError, ValueError):
    """A model card, its metrics file or a name in one that does not match the format."""
