"""The storage service: a directory whose files are properties (``docs/storage.md``).

* :class:`Storage` — the service (``files``, ``file`` by ``name``, ``info``, ``find``, ``remove``);
  :class:`StorageService` — the backend that serves it (``Storage.served_by``).
* :mod:`services.apps.storage.names` — the file name grammar; :mod:`services.apps.storage.disk` — the
  blocking, directory-bound file operations; :mod:`services.apps.storage.watcher` — changes on disk;
  :mod:`services.apps.storage.find` — the ``find`` query.
"""

from services.apps.storage.names import check_name
from services.apps.storage.service import MAX_FILE_SIZE, MAX_LISTED, Storage, StorageService

__all__ = ["MAX_FILE_SIZE", "MAX_LISTED", "Storage", "StorageService", "check_name"]
