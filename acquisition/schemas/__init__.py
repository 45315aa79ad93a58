"""Topics and message layouts of a recorded session (ros2msg schemas, CDR payloads)."""

from acquisition.schemas.cdr import Field, FixedMessage, SchemaError
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.topics import Topic, session_topics

__all__ = ["Event", "EventKind", "Field", "FixedMessage", "SchemaError", "Topic", "session_topics"]
