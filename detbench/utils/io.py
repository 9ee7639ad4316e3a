"""The file helpers under one import path, for code that imports them from `detbench.utils.io`.

Each lives in the module of its job, which new code imports directly: detbench.utils.atomic
(atomic writes and JSON), detbench.utils.folder_ownership (which writer owns a folder; replace,
claim and clear checks), detbench.utils.folder_locks (the lock and the claim of a folder a process
writes into) and detbench.utils.staged_folders (folders built beside the old one and swapped in).
"""
from detbench.utils.atomic import (
    DiskFullError, atomic_path, atomic_save, atomic_write_bytes, atomic_write_json, atomic_write_text, read_json,
    remove_stale_temporaries, to_json,
)
from detbench.utils.folder_locks import FolderLock, acquire_folder_lock, claim_folder
from detbench.utils.folder_ownership import (
    LOCK_FILE, OWNER_FILE, FolderInUse, FolderKind, FolderNotReplaceable, check_claimable, check_replaceable,
    clear_folder, folder_owner, write_owner,
)
from detbench.utils.staged_folders import STAGED_NEW, STAGED_OLD, pid_alive, recover_staged, staged_folder, swap_in

__all__ = [
    "DiskFullError", "atomic_path", "atomic_save", "atomic_write_bytes", "atomic_write_json", "atomic_write_text",
    "read_json", "remove_stale_temporaries", "to_json", "FolderLock", "acquire_folder_lock", "claim_folder",
    "LOCK_FILE", "OWNER_FILE", "FolderInUse", "FolderKind", "FolderNotReplaceable", "check_claimable",
    "check_replaceable", "clear_folder", "folder_owner", "write_owner", "STAGED_NEW", "STAGED_OLD", "pid_alive",
    "recover_staged", "staged_folder", "swap_in",
]
