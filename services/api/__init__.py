"""The platform's REST API: users, lab resources, recordings, jobs and their results."""
