"""The app-facing tracker: ``Tracker`` (one lock, the public API) and its five thin views
(``events``, ``live``, ``object``, ``world``, ``export``), plus the table of old member names
kept for one release. Everything below (the loop, mapping, object mode, live intake,
persistence) is reached through here."""
