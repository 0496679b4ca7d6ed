"""Station database: SQLAlchemy models, Alembic migrations, the event writer, the repository.

    from db import Database, DbWriter
    db = Database("sqlite:///var/station.db"); db.upgrade(); db.mark_interrupted()
    writer = DbWriter(db); writer.bind_run(batch_id, slot, run_id); writer.submit(event)
"""

from db.database import Database, ResumePoint, RunPoint
from db.writer import CommitInfo, DbWriter

__all__ = ["Database", "DbWriter", "ResumePoint", "RunPoint", "CommitInfo"]
