"""Import a repository script (a benchmark, a tool) by its path, for the tests beside it."""
import importlib.util
from pathlib import Path
import sys
from types import ModuleType


def load_script(path: Path, name: str) -> ModuleType:
    """Execute the script at ``path`` as module ``name`` (in sys.modules); return it."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module          # dataclasses and pickling look their module up there
    spec.loader.exec_module(module)
    return module
