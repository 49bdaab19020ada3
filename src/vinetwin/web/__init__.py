"""The Viser authoring app (`vinetwin web`, docs/web.md): `session` holds the editing logic
(testable without a browser), `app` binds it to the page."""
