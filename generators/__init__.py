"""Built-in object classes: one module per class, each registering one sampling table.

Modules here are discovered automatically by :mod:`articulated_dataset.registry`; adding a
class means adding ``urdf_templates/<name>.urdf.xacro`` and a module here that calls
:func:`articulated_dataset.registry.register`.

Numbers are the paper's Appendix A (Tables 3 and 4) converted to SI: geometry in metres
(the paper lists cm), prismatic configuration in metres (the paper lists cm).
"""
