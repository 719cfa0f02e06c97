"""Study records: database models and repository, migrations, headless study runner, statistics, export.

Import the pieces from their modules (``app.study.repository``, ``app.study.db``, ...); this package does
not import SQLAlchemy or start anything on import.
"""
