"""motok.text"""
